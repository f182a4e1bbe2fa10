//! One optimizer step: the epoch's permutation of the training hit rays,
//! the batch assembled on the CPU from `SampleRng` streams keyed by
//! (seed, step), the forward and backward pass with its losses, and the Adam
//! optimizer.

use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use nppp_estimator::{EXIT_FEATURES, VERTEX_FEATURES};
use nppp_geom::SampleRng;

use super::TrainConfig;
use crate::data::TrainingData;
use crate::features::INPUT_FEATURES;
use crate::loss::{
    bce_with_logits, chamfer_from_dists, energy_distance_trainable, pairwise_sq_dists,
};
use crate::model::NpppModel;

// Stream ids of the per-step random choices.
const STREAM_PERM: u64 = 0x9E41;
const STREAM_BATCH: u64 = 0xBA7C;
const STREAM_NOISE: u64 = 0x7015;
const STREAM_MASK: u64 = 0x3A5C;
const STREAM_VERTEX_NOISE: u64 = 0x7E27;

/// One step's input, assembled on the CPU.
pub(super) struct Batch {
    features: Vec<f32>,
    real: Vec<f32>,
    noise: Vec<f32>,
    mask_features: Vec<f32>,
    mask_labels: Vec<f32>,
    /// The picked vertices of the same walks as `real`, and the vertex
    /// head's noise (both empty without the head).
    real_vertices: Vec<f32>,
    vertex_noise: Vec<f32>,
    b: usize,
    k: usize,
    bm: usize,
}

/// The permutation of the training hit rays for one epoch.
pub(super) fn epoch_permutation(seed: u64, epoch: u64, n: usize) -> Vec<u32> {
    let mut rng = SampleRng::new(seed, epoch, STREAM_PERM);
    let mut p: Vec<u32> = (0..n as u32).collect();
    for i in (1..n).rev() {
        let j = (rng.next_u64() % (i as u64 + 1)) as usize;
        p.swap(i, j);
    }
    p
}

pub(super) fn make_batch(
    cfg: &TrainConfig,
    data: &TrainingData,
    perm: &[u32],
    step: u64,
    spe: usize,
) -> Batch {
    let tr = &data.train;
    let n_hit = tr.hits();
    let b = cfg.batch;
    let kf = data.k;
    let k = cfg.k.min(kf);
    let nd = cfg.model.noise_dim;
    let in_epoch = (step % spe as u64) as usize;
    let mut rng = SampleRng::new(cfg.seed, step, STREAM_BATCH);
    let mut features = Vec::with_capacity(b * INPUT_FEATURES);
    let mut real = Vec::with_capacity(b * k * EXIT_FEATURES);
    let with_vertices = cfg.model.vertex_head;
    let mut real_vertices = Vec::with_capacity(if with_vertices {
        b * k * VERTEX_FEATURES
    } else {
        0
    });
    let mut idx: Vec<u32> = (0..kf as u32).collect();
    for j in 0..b {
        let h = perm[(in_epoch * b + j) % n_hit] as usize;
        let ray = tr.hit_index[h];
        features.extend_from_slice(&tr.features[ray * INPUT_FEATURES..(ray + 1) * INPUT_FEATURES]);
        let exits = &tr.exits[h * kf * EXIT_FEATURES..(h + 1) * kf * EXIT_FEATURES];
        let vertices: &[f32] = if with_vertices {
            &tr.vertices[h * kf * VERTEX_FEATURES..(h + 1) * kf * VERTEX_FEATURES]
        } else {
            &[]
        };
        if k == kf {
            real.extend_from_slice(exits);
            real_vertices.extend_from_slice(vertices);
        } else {
            // Partial Fisher-Yates: k distinct exits of the file's kf.
            for i in 0..k {
                let r = i + (rng.next_u64() % (kf - i) as u64) as usize;
                idx.swap(i, r);
                let e = idx[i] as usize;
                real.extend_from_slice(&exits[e * EXIT_FEATURES..(e + 1) * EXIT_FEATURES]);
                if with_vertices {
                    real_vertices.extend_from_slice(
                        &vertices[e * VERTEX_FEATURES..(e + 1) * VERTEX_FEATURES],
                    );
                }
            }
        }
    }
    let mut nrng = SampleRng::new(cfg.seed, step, STREAM_NOISE);
    let noise: Vec<f32> = (0..b * k * nd).map(|_| nrng.normal()).collect();
    let vertex_noise: Vec<f32> = if with_vertices {
        let mut vrng = SampleRng::new(cfg.seed, step, STREAM_VERTEX_NOISE);
        (0..b * k * nd).map(|_| vrng.normal()).collect()
    } else {
        Vec::new()
    };
    let mut mrng = SampleRng::new(cfg.seed, step, STREAM_MASK);
    let bm = cfg.mask_batch;
    let mut mask_features = Vec::with_capacity(bm * INPUT_FEATURES);
    let mut mask_labels = Vec::with_capacity(bm);
    for _ in 0..bm {
        let i = (mrng.next_u64() % tr.len() as u64) as usize;
        mask_features.extend_from_slice(&tr.features[i * INPUT_FEATURES..(i + 1) * INPUT_FEATURES]);
        mask_labels.push(tr.hit[i] as u8 as f32);
    }
    Batch {
        features,
        real,
        noise,
        mask_features,
        mask_labels,
        real_vertices,
        vertex_noise,
        b,
        k,
        bm,
    }
}

/// Loss values of one step: total, chamfer, energy, bce.
type StepLosses = [f32; 4];

pub(super) fn train_step(
    model: NpppModel,
    optim: &mut ModuleOptimizer,
    cfg: &TrainConfig,
    lr: f64,
    batch: Batch,
    device: &Device,
) -> std::result::Result<(NpppModel, StepLosses), (NpppModel, f32)> {
    let Batch {
        features,
        real,
        noise,
        mask_features,
        mask_labels,
        real_vertices,
        vertex_noise,
        b,
        k,
        bm,
    } = batch;
    let nd = cfg.model.noise_dim;
    let feats = Tensor::<2>::from_data(TensorData::new(features, [b, INPUT_FEATURES]), device);
    let real = Tensor::<3>::from_data(TensorData::new(real, [b, k, EXIT_FEATURES]), device);
    let noise = Tensor::<2>::from_data(TensorData::new(noise, [b * k, nd]), device);
    let z = model.encode(feats);
    let generated = model.generate_from_latent(z.clone(), noise, k);
    let (chamfer, energy) = set_distances(generated, real, cfg.energy_weight, device);
    // The vertex head's term: the same distances on the picked vertices,
    // in the total loss only (log.csv's columns stay the exits').
    let vertex_noise = (!vertex_noise.is_empty())
        .then(|| Tensor::<2>::from_data(TensorData::new(vertex_noise, [b * k, nd]), device));
    let vertex_term =
        match vertex_noise.and_then(|vn| model.generate_vertices_from_latent(z, vn, k)) {
            Some(gv) => {
                let rv = Tensor::<3>::from_data(
                    TensorData::new(real_vertices, [b, k, VERTEX_FEATURES]),
                    device,
                );
                let (c, e) = set_distances(gv, rv, cfg.energy_weight, device);
                (c + e.mul_scalar(cfg.energy_weight)).mul_scalar(cfg.vertex_weight)
            }
            None => Tensor::<1>::zeros([1], device),
        };
    let mf = Tensor::<2>::from_data(TensorData::new(mask_features, [bm, INPUT_FEATURES]), device);
    let ml = Tensor::<1>::from_data(TensorData::new(mask_labels, [bm]), device);
    let bce = bce_with_logits(model.mask_logits(mf), ml);
    let loss = chamfer.clone()
        + energy.clone().mul_scalar(cfg.energy_weight)
        + bce.clone().mul_scalar(cfg.mask_weight)
        + vertex_term;
    // One read-back per step: the values for the log and the finiteness check.
    let values = Tensor::cat(
        vec![
            loss.clone().detach(),
            chamfer.detach(),
            energy.detach(),
            bce.detach(),
        ],
        0,
    )
    .into_data()
    .try_into_vec::<f32>()
    .unwrap_or_else(|_| vec![f32::NAN; 4]);
    let v: StepLosses = [values[0], values[1], values[2], values[3]];
    if !v.iter().all(|x| x.is_finite()) {
        return Err((model, v[0]));
    }
    let grads = GradientsParams::from_grads(loss.backward(), &model);
    let model = optim.step(lr, model, grads);
    Ok((model, v))
}

/// Chamfer and (with a positive `energy_weight`, else zero) the trainable
/// energy distance between each ray's generated and real sets, from one
/// pairwise distance matrix.
fn set_distances(
    generated: Tensor<3>,
    real: Tensor<3>,
    energy_weight: f32,
    device: &Device,
) -> (Tensor<1>, Tensor<1>) {
    let d = pairwise_sq_dists(generated.clone(), real);
    let chamfer = chamfer_from_dists(d.clone());
    let energy = if energy_weight > 0.0 {
        energy_distance_trainable(d, generated)
    } else {
        Tensor::<1>::zeros([1], device)
    };
    (chamfer, energy)
}

pub(super) fn make_optimizer(cfg: &TrainConfig) -> ModuleOptimizer {
    let mut a = AdamConfig::new()
        .with_beta_1(cfg.beta_1)
        .with_beta_2(cfg.beta_2)
        .with_epsilon(cfg.epsilon);
    if cfg.grad_clip_norm > 0.0 {
        a = a.with_grad_clipping(Some(burn::grad_clipping::GradientClippingConfig::Norm(
            cfg.grad_clip_norm,
        )));
    }
    a.init()
}
