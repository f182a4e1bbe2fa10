//! The baked decoder as a Burn module, for rendering: the renderer gathers
//! every estimator query of a wavefront step and runs them as one batch, so
//! the same module runs on a GPU (wgpu) when there is one and on a Burn CPU
//! backend otherwise. It is a decoder backend of the estimator interface
//! ([`nppp_estimator::ExitDecoder`], attached with
//! `EstimatorSampler::set_decoder`); the plain-Rust decoder in
//! nppp-estimator is the default, and this one must give the same numbers
//! (tested).

use crate::backend::BackendKind;
use crate::model::MlpNet;
use anyhow::{Result, anyhow};
use burn::module::Param;
use burn::nn::Linear;
use burn::tensor::{Device, Tensor, TensorData};
use nppp_estimator::{ExitDecoder, Mlp};

/// A decoder loaded into Burn on one device.
pub struct BurnDecoder {
    net: MlpNet,
    device: Device,
    inputs: usize,
    outputs: usize,
    backend: BackendKind,
    /// "burn-" and the backend, for reports.
    name: String,
}

impl MlpNet {
    /// The inverse of [`MlpNet::to_mlp`]: Burn stores `[inputs][outputs]`.
    pub fn from_mlp(mlp: &Mlp, device: &Device) -> Result<Self> {
        mlp.validate().map_err(|e| anyhow!("decoder: {e}"))?;
        let layers = mlp
            .layers
            .iter()
            .map(|l| {
                let mut w = vec![0.0f32; l.inputs * l.outputs];
                for o in 0..l.outputs {
                    for i in 0..l.inputs {
                        w[i * l.outputs + o] = l.weight[o * l.inputs + i];
                    }
                }
                Linear {
                    weight: Param::from_data(TensorData::new(w, [l.inputs, l.outputs]), device),
                    bias: Some(Param::from_data(
                        TensorData::new(l.bias.clone(), [l.outputs]),
                        device,
                    )),
                }
            })
            .collect();
        Ok(Self { layers })
    }
}

impl BurnDecoder {
    pub fn new(mlp: &Mlp, backend: BackendKind) -> Result<Self> {
        let device = backend.device()?;
        let net = MlpNet::from_mlp(mlp, &device)?;
        Ok(Self {
            net,
            device,
            inputs: mlp.inputs(),
            outputs: mlp.outputs(),
            backend,
            name: format!("burn-{backend}"),
        })
    }

    pub fn backend(&self) -> BackendKind {
        self.backend
    }

    /// `input`: `rows` rows of the decoder's input width; writes `rows` rows of its output width.
    pub fn forward(&self, input: &[f32], rows: usize, output: &mut [f32]) -> Result<()> {
        if rows == 0 {
            return Ok(());
        }
        if input.len() < rows * self.inputs || output.len() < rows * self.outputs {
            return Err(anyhow!(
                "decoder batch: {} inputs / {} outputs for {rows} rows",
                input.len(),
                output.len()
            ));
        }
        let x = Tensor::<2>::from_data(
            TensorData::new(input[..rows * self.inputs].to_vec(), [rows, self.inputs]),
            &self.device,
        );
        let y = self
            .net
            .forward(x)
            .into_data()
            .try_to_vec::<f32>()
            .map_err(|e| anyhow!("decoder output: {e:?}"))?;
        output[..rows * self.outputs].copy_from_slice(&y);
        Ok(())
    }
}

impl ExitDecoder for BurnDecoder {
    fn decode(&self, input: &[f32], rows: usize, output: &mut [f32]) -> Result<(), String> {
        self.forward(input, rows, output).map_err(|e| e.to_string())
    }

    fn name(&self) -> &str {
        &self.name
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nppp_estimator::Dense;
    use nppp_geom::SampleRng;

    fn random_mlp(widths: &[usize], rng: &mut SampleRng) -> Mlp {
        Mlp {
            layers: widths
                .windows(2)
                .map(|w| Dense {
                    inputs: w[0],
                    outputs: w[1],
                    weight: (0..w[0] * w[1]).map(|_| rng.normal() * 0.3).collect(),
                    bias: (0..w[1]).map(|_| rng.normal() * 0.1).collect(),
                })
                .collect(),
        }
    }

    #[test]
    fn burn_decoder_matches_the_cpu_decoder() {
        let mut rng = SampleRng::from_seed(5);
        let mlp = random_mlp(&[32, 64, 64, 13], &mut rng);
        let rows = 300;
        let input: Vec<f32> = (0..rows * 32).map(|_| rng.normal()).collect();
        let mut want = vec![0.0; rows * 13];
        mlp.forward_batch(&input, &mut want);
        for backend in [BackendKind::Ndarray, BackendKind::Flex] {
            let dec = BurnDecoder::new(&mlp, backend).unwrap();
            let mut got = vec![0.0; rows * 13];
            dec.forward(&input, rows, &mut got).unwrap();
            for (a, b) in got.iter().zip(&want) {
                assert!(
                    (a - b).abs() <= 1e-4 * (1.0 + b.abs()),
                    "{backend}: {a} vs {b}"
                );
            }
        }
    }
}
