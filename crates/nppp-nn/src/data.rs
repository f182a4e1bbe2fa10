//! Training data in the layout the trainer wants: ray features precomputed,
//! exits already encoded with the [`ExitTransform`] and packed into one flat
//! array, split deterministically into a training and a held-out part.

use anyhow::{Result, bail};
use nppp_estimator::{EXIT_FEATURES, Exit, ExitTransform, VERTEX_FEATURES, VertexTransform};
use nppp_geom::SpherePair;

use crate::features::{INPUT_FEATURES, ray_features};

/// One input ray as the data generator produced it: its chord, whether it
/// hits the mesh (the mask label) and, for a hit, its k exits.
pub type RaySample = nppp_estimator::RayRecord;

/// Part of the data (training or held-out).
#[derive(Clone, Debug, Default)]
pub struct DataSplit {
    pub pairs: Vec<SpherePair>,
    pub hit: Vec<bool>,
    /// `[pairs.len()][INPUT_FEATURES]`.
    pub features: Vec<f32>,
    /// Indices (into `pairs`) of the rays that hit.
    pub hit_index: Vec<usize>,
    /// `[hit_index.len()][k][EXIT_FEATURES]`, encoded with the transform.
    pub exits: Vec<f32>,
    /// The raw exits of the hit rays (`[hit_index.len()][k]`); kept only for
    /// the held-out part, where the evaluation needs physical throughputs.
    pub raw_exits: Vec<Exit>,
    /// `[hit_index.len()][k][VERTEX_FEATURES]`, encoded with the vertex
    /// transform; empty when the data has no picked vertices.
    pub vertices: Vec<f32>,
}

impl DataSplit {
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    pub fn hits(&self) -> usize {
        self.hit_index.len()
    }
}

/// Everything the trainer needs from a data file.
#[derive(Clone, Debug)]
pub struct TrainingData {
    /// Exits per hit ray in the file.
    pub k: usize,
    pub transform: ExitTransform,
    /// The picked vertices' transform, when the data has vertices (the
    /// model then trains its vertex head).
    pub vertex_transform: Option<VertexTransform>,
    pub train: DataSplit,
    pub heldout: DataSplit,
}

/// Whether ray `index` of a file belongs to the held-out part: every
/// `holdout_every`-th ray, so the split depends on nothing but the file.
pub fn is_heldout(index: usize, holdout_every: usize) -> bool {
    holdout_every > 0 && index % holdout_every == holdout_every - 1
}

fn check_ray(i: usize, r: &RaySample, k: usize) -> Result<()> {
    if !r
        .pair
        .0
        .iter()
        .all(|x| x.is_finite() && (-1e-3..=1.0 + 1e-3).contains(x))
    {
        bail!(
            "ray {i}: sphere-pair coordinates {:?} are not in [0, 1]",
            r.pair.0
        );
    }
    if !r.vertices.is_empty() && r.vertices.len() != r.exits.len() {
        bail!(
            "ray {i}: {} picked vertices for {} exits",
            r.vertices.len(),
            r.exits.len()
        );
    }
    if r.hit {
        if r.exits.len() != k {
            bail!(
                "ray {i}: a hit with {} exits, expected k = {k}",
                r.exits.len()
            );
        }
        for (j, e) in r.exits.iter().enumerate() {
            let ok = e.position.is_finite()
                && e.direction.is_finite()
                && e.throughput.is_finite()
                && e.radiance.is_finite()
                && e.throughput.min_element() >= 0.0
                && e.radiance.min_element() >= 0.0;
            if !ok {
                bail!(
                    "ray {i}, exit {j}: non-finite or negative values (position {}, direction \
                     {}, throughput {}, radiance {})",
                    e.position,
                    e.direction,
                    e.throughput,
                    e.radiance
                );
            }
        }
    }
    Ok(())
}

/// Validates and encodes rays into a split. `keep_raw` keeps the physical
/// exits too (the evaluation needs them; training does not).
pub fn encode_split(
    rays: Vec<RaySample>,
    k: usize,
    transform: &ExitTransform,
    vertex_transform: Option<&VertexTransform>,
    keep_raw: bool,
) -> Result<DataSplit> {
    if k == 0 {
        bail!("the data declares k = 0 exits per ray");
    }
    let mut s = DataSplit::default();
    for (i, r) in rays.into_iter().enumerate() {
        check_ray(i, &r, k)?;
        if r.hit {
            s.hit_index.push(s.pairs.len());
            s.exits.reserve(k * EXIT_FEATURES);
            for e in &r.exits {
                s.exits.extend_from_slice(&transform.encode(e));
            }
            if keep_raw {
                s.raw_exits.extend_from_slice(&r.exits);
            }
            if let Some(vt) = vertex_transform {
                if r.vertices.len() != k {
                    bail!("ray {i}: a hit without its {k} picked vertices in data that has them");
                }
                s.vertices.reserve(k * VERTEX_FEATURES);
                for v in &r.vertices {
                    s.vertices.extend_from_slice(&vt.encode(v));
                }
            }
        }
        s.pairs.push(r.pair);
        s.hit.push(r.hit);
    }
    s.features = ray_features(&s.pairs);
    debug_assert_eq!(s.features.len(), s.pairs.len() * INPUT_FEATURES);
    Ok(s)
}

impl TrainingData {
    /// Splits, validates and encodes the rays. `k` is the exits per hit the
    /// file declares; the transform is fitted on the training exits only, so
    /// the held-out numbers are honest.
    pub fn build(rays: Vec<RaySample>, k: usize, holdout_every: usize) -> Result<Self> {
        if holdout_every < 2 {
            bail!("holdout_every must be at least 2 (got {holdout_every})");
        }
        for (i, r) in rays.iter().enumerate() {
            check_ray(i, r, k)?;
        }
        let transform = ExitTransform::fit(
            rays.iter()
                .enumerate()
                .filter(|(i, r)| r.hit && !is_heldout(*i, holdout_every))
                .flat_map(|(_, r)| r.exits.iter()),
        );
        // Vertices are learned when every hit carries them (a data set
        // without them, version 1 or a glass object, trains the exits alone).
        let has_vertices =
            rays.iter().any(|r| r.hit) && rays.iter().all(|r| !r.hit || !r.vertices.is_empty());
        let vertex_transform = has_vertices.then(|| {
            VertexTransform::fit(
                rays.iter()
                    .enumerate()
                    .filter(|(i, r)| r.hit && !is_heldout(*i, holdout_every))
                    .flat_map(|(_, r)| r.vertices.iter()),
            )
        });
        let (mut train, mut held) = (Vec::new(), Vec::new());
        for (i, r) in rays.into_iter().enumerate() {
            if is_heldout(i, holdout_every) {
                held.push(r);
            } else {
                train.push(r);
            }
        }
        let train = encode_split(train, k, &transform, vertex_transform.as_ref(), false)?;
        let heldout = encode_split(held, k, &transform, vertex_transform.as_ref(), true)?;
        if train.hits() == 0 {
            bail!("the training part has no ray that hits the mesh: nothing to learn exits from");
        }
        Ok(Self {
            k,
            transform,
            vertex_transform,
            train,
            heldout,
        })
    }
}
