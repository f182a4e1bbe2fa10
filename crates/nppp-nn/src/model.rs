//! The three networks of the estimator as Burn modules, and the exact export
//! of the decoder to the renderer's plain-Rust [`Mlp`].
//!
//! There is no backend type parameter: in Burn 0.22 the backend lives in the
//! tensors' `Device`, so the same module trains on NdArray, Flex or Wgpu.

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};
use nppp_estimator::{Dense, EXIT_FEATURES, Mlp, VERTEX_FEATURES};
use nppp_geom::SampleRng;

use crate::features::INPUT_FEATURES;

/// Shapes of the three networks. Saved as `model_config.json` beside the
/// weights, because the weights file alone does not say how to rebuild the
/// module it is loaded into.
#[derive(Config, Debug, PartialEq)]
pub struct ModelConfig {
    /// Length of z; the baked latent grid stores this many channels per node.
    #[config(default = 16)]
    pub latent_dim: usize,
    /// Length of r ~ N(0, 1) fed to the decoder next to z.
    #[config(default = 16)]
    pub noise_dim: usize,
    /// The encoder is baked away, so it can be wide: it only costs training time.
    #[config(default = 256)]
    pub encoder_width: usize,
    /// Hidden layers of the encoder.
    #[config(default = 4)]
    pub encoder_layers: usize,
    /// The decoder runs per sample in the renderer: keep it a few thousand
    /// multiply-adds.
    #[config(default = 64)]
    pub decoder_width: usize,
    #[config(default = 3)]
    pub decoder_layers: usize,
    /// The mask boundary of a thin, knotted shape is intricate; 256 wide
    /// learned it clearly better than 128 for 10% more time per step.
    #[config(default = 256)]
    pub mask_width: usize,
    #[config(default = 3)]
    pub mask_layers: usize,
    /// Length of the input feature vector; checked on load so that a model
    /// trained with another feature map is refused rather than misread.
    #[config(default = 45)]
    pub input_features: usize,
    /// A second decoder, of the decoder's shape, that draws the vertex of
    /// the skipped path picked for next-event estimation
    /// ([`nppp_estimator::PickedVertex`]) from the same latent with its own
    /// noise. On when the training data has vertices.
    #[config(default = false)]
    pub vertex_head: bool,
}

/// The largest latent, noise or hidden layer size a model may have: larger
/// is a typo or a damaged file, not a network this pipeline trains.
pub const MAX_LAYER_SIZE: usize = 8192;

impl ModelConfig {
    /// Rejects shapes that cannot be built or that a file could carry by
    /// mistake (zero or absurd sizes).
    pub fn validate(&self) -> Result<()> {
        let dims = [
            ("latent_dim", self.latent_dim),
            ("noise_dim", self.noise_dim),
            ("encoder_width", self.encoder_width),
            ("decoder_width", self.decoder_width),
            ("mask_width", self.mask_width),
        ];
        for (name, v) in dims {
            if v == 0 || v > MAX_LAYER_SIZE {
                bail!("model config: {name} = {v} is out of range 1..={MAX_LAYER_SIZE}");
            }
        }
        for (name, v) in [
            ("encoder_layers", self.encoder_layers),
            ("decoder_layers", self.decoder_layers),
            ("mask_layers", self.mask_layers),
        ] {
            if v > 64 {
                bail!("model config: {name} = {v} is out of range 0..=64");
            }
        }
        if self.input_features != INPUT_FEATURES {
            bail!(
                "model config: input_features = {} but this build computes {} features per ray \
                 (the model was trained with another feature map)",
                self.input_features,
                INPUT_FEATURES
            );
        }
        Ok(())
    }

    /// Multiply-adds of one decoder evaluation (what the renderer pays per sample).
    pub fn decoder_macs(&self) -> usize {
        layer_widths(
            self.latent_dim + self.noise_dim,
            self.decoder_width,
            self.decoder_layers,
            EXIT_FEATURES,
        )
        .windows(2)
        .map(|w| w[0] * w[1])
        .sum()
    }
}

fn layer_widths(input: usize, width: usize, hidden: usize, output: usize) -> Vec<usize> {
    let mut w = vec![input];
    w.extend(std::iter::repeat_n(width, hidden));
    w.push(output);
    w
}

/// Linear layers with ReLU between them and none after the last: exactly the
/// shape [`Mlp`] evaluates, so the decoder exports without approximation.
#[derive(Module, Debug)]
pub struct MlpNet {
    pub layers: Vec<Linear>,
}

impl MlpNet {
    /// Initializes from the project's own RNG, not Burn's, so that the
    /// initial weights are identical on every backend and thread count.
    /// Hidden layers use He-uniform (they feed a ReLU); the output layer the
    /// smaller 1/sqrt(fan_in) bound so that initial outputs are O(1) in the
    /// standardized target space. Biases start at zero.
    pub fn init(widths: &[usize], rng: &mut SampleRng, device: &Device) -> Self {
        let n = widths.len() - 1;
        let layers = (0..n)
            .map(|i| {
                let (fan_in, fan_out) = (widths[i], widths[i + 1]);
                let bound = if i + 1 < n {
                    (6.0 / fan_in as f32).sqrt()
                } else {
                    (1.0 / fan_in as f32).sqrt()
                };
                let w: Vec<f32> = (0..fan_in * fan_out)
                    .map(|_| (2.0 * rng.uniform() - 1.0) * bound)
                    .collect();
                Linear {
                    weight: Param::from_data(TensorData::new(w, [fan_in, fan_out]), device),
                    bias: Some(Param::from_data(
                        TensorData::new(vec![0.0f32; fan_out], [fan_out]),
                        device,
                    )),
                }
            })
            .collect();
        Self { layers }
    }

    pub fn forward(&self, mut x: Tensor<2>) -> Tensor<2> {
        let last = self.layers.len() - 1;
        for (i, l) in self.layers.iter().enumerate() {
            x = l.forward(x);
            if i < last {
                x = relu(x);
            }
        }
        x
    }

    /// Copies the weights into the renderer's layout. Burn stores a Linear
    /// weight as `[inputs][outputs]`; [`Dense`] wants `[outputs][inputs]`.
    pub fn to_mlp(&self) -> Result<Mlp> {
        let mut layers = Vec::with_capacity(self.layers.len());
        for (i, l) in self.layers.iter().enumerate() {
            let [inputs, outputs] = l.weight.val().dims();
            let w = l
                .weight
                .val()
                .into_data()
                .try_into_vec::<f32>()
                .map_err(|e| anyhow::anyhow!("layer {i} weight: {e:?}"))?;
            let mut weight = vec![0.0f32; inputs * outputs];
            for r in 0..inputs {
                for c in 0..outputs {
                    weight[c * inputs + r] = w[r * outputs + c];
                }
            }
            let bias = match &l.bias {
                Some(b) => b
                    .val()
                    .into_data()
                    .try_into_vec::<f32>()
                    .map_err(|e| anyhow::anyhow!("layer {i} bias: {e:?}"))?,
                None => vec![0.0; outputs],
            };
            layers.push(Dense {
                inputs,
                outputs,
                weight,
                bias,
            });
        }
        let mlp = Mlp { layers };
        mlp.validate()
            .map_err(|e| anyhow::anyhow!("exported MLP is invalid: {e}"))?;
        Ok(mlp)
    }
}

/// `net` on k copies of each row of z (`[B, latent]`), copy j of row i with
/// noise row `i * k + j` of `noise` (`[B*k, noise_dim]`): one batched
/// forward over B*k rows. Returns `[B, k, outputs]`.
fn decode_k(net: &MlpNet, z: Tensor<2>, noise: Tensor<2>, k: usize, outputs: usize) -> Tensor<3> {
    let [b, l] = z.dims();
    let zk = z.unsqueeze_dim::<3>(1).repeat_dim(1, k).reshape([b * k, l]);
    let x = Tensor::cat(vec![zk, noise], 1);
    net.forward(x).reshape([b, k, outputs])
}

/// Encoder (ray -> z), decoder ((z, r) -> encoded exit) and mask network
/// (ray -> logit). The mask network is separate from the encoder, as in the
/// thesis: it trains on every ray (hits and misses) while the encoder only
/// sees hits, and neither task's gradients disturb the other. The optional
/// vertex decoder ((z, r') -> encoded picked vertex) shares the latent, so
/// the baked grid serves both.
#[derive(Module, Debug)]
pub struct NpppModel {
    pub encoder: MlpNet,
    pub decoder: MlpNet,
    pub mask: MlpNet,
    pub vertex_decoder: Option<MlpNet>,
}

impl NpppModel {
    /// A freshly initialized model; identical for equal seeds on any backend.
    pub fn init(cfg: &ModelConfig, seed: u64, device: &Device) -> Result<Self> {
        cfg.validate()?;
        let mut rng = SampleRng::new(seed, 0x1417, 0);
        let encoder = MlpNet::init(
            &layer_widths(
                cfg.input_features,
                cfg.encoder_width,
                cfg.encoder_layers,
                cfg.latent_dim,
            ),
            &mut rng,
            device,
        );
        let decoder = MlpNet::init(
            &layer_widths(
                cfg.latent_dim + cfg.noise_dim,
                cfg.decoder_width,
                cfg.decoder_layers,
                EXIT_FEATURES,
            ),
            &mut rng,
            device,
        );
        let mask = MlpNet::init(
            &layer_widths(cfg.input_features, cfg.mask_width, cfg.mask_layers, 1),
            &mut rng,
            device,
        );
        // Drawn last, so a model without the head starts from the same
        // weights as before it existed.
        let vertex_decoder = cfg.vertex_head.then(|| {
            MlpNet::init(
                &layer_widths(
                    cfg.latent_dim + cfg.noise_dim,
                    cfg.decoder_width,
                    cfg.decoder_layers,
                    VERTEX_FEATURES,
                ),
                &mut rng,
                device,
            )
        });
        Ok(Self {
            encoder,
            decoder,
            mask,
            vertex_decoder,
        })
    }

    /// `[B, F]` features -> `[B, latent]`.
    pub fn encode(&self, features: Tensor<2>) -> Tensor<2> {
        self.encoder.forward(features)
    }

    /// The k decoder copies as one batched forward: z is repeated k times
    /// (shared weights, one matmul over B*k rows) and each copy gets its own
    /// row of `noise` (`[B*k, noise_dim]`). Returns `[B, k, EXIT_FEATURES]`.
    pub fn generate_from_latent(&self, z: Tensor<2>, noise: Tensor<2>, k: usize) -> Tensor<3> {
        decode_k(&self.decoder, z, noise, k, EXIT_FEATURES)
    }

    /// The vertex head's k draws per ray, as [`Self::generate_from_latent`]
    /// (`None` without the head). Returns `[B, k, VERTEX_FEATURES]`.
    pub fn generate_vertices_from_latent(
        &self,
        z: Tensor<2>,
        noise: Tensor<2>,
        k: usize,
    ) -> Option<Tensor<3>> {
        let head = self.vertex_decoder.as_ref()?;
        Some(decode_k(head, z, noise, k, VERTEX_FEATURES))
    }

    pub fn generate(&self, features: Tensor<2>, noise: Tensor<2>, k: usize) -> Tensor<3> {
        self.generate_from_latent(self.encode(features), noise, k)
    }

    /// `[B, F]` features -> `[B]` mask logits (positive = the ray hits the mesh).
    pub fn mask_logits(&self, features: Tensor<2>) -> Tensor<1> {
        let [b, _] = features.dims();
        self.mask.forward(features).reshape([b])
    }

    /// The decoder in the renderer's format.
    pub fn export_decoder(&self) -> Result<Mlp> {
        self.decoder.to_mlp().context("exporting the decoder")
    }

    /// The vertex decoder in the renderer's format, if the model has one.
    pub fn export_vertex_decoder(&self) -> Result<Option<Mlp>> {
        self.vertex_decoder
            .as_ref()
            .map(|h| h.to_mlp().context("exporting the vertex decoder"))
            .transpose()
    }
}
