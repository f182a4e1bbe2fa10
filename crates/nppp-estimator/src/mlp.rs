//! A plain-Rust multilayer perceptron: the decoder as the renderer runs it on
//! the CPU, and the weight layout the baked file stores.

use serde::{Deserialize, Serialize};

/// A fully connected layer; `weight` is row-major `[outputs][inputs]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dense {
    pub inputs: usize,
    pub outputs: usize,
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Layers with ReLU between them and none after the last one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct Mlp {
    pub layers: Vec<Dense>,
}

impl Mlp {
    pub fn inputs(&self) -> usize {
        self.layers.first().map_or(0, |l| l.inputs)
    }

    pub fn outputs(&self) -> usize {
        self.layers.last().map_or(0, |l| l.outputs)
    }

    /// Multiply-adds per row: what one decoder row costs.
    pub fn multiply_adds(&self) -> usize {
        self.layers.iter().map(|l| l.inputs * l.outputs).sum()
    }

    /// Widest layer, i.e. the scratch size `forward` needs per row.
    pub fn max_width(&self) -> usize {
        self.layers.iter().map(|l| l.inputs.max(l.outputs)).max().unwrap_or(0)
    }

    /// Checks that consecutive layers chain and that weight arrays have the
    /// sizes they claim; returns a description of the first problem.
    pub fn validate(&self) -> Result<(), String> {
        if self.layers.is_empty() {
            return Err("no layers".into());
        }
        for (i, l) in self.layers.iter().enumerate() {
            if l.inputs == 0 || l.outputs == 0 {
                return Err(format!("layer {i} has a zero dimension"));
            }
            if l.weight.len() != l.inputs * l.outputs || l.bias.len() != l.outputs {
                return Err(format!("layer {i} weight/bias sizes do not match {}x{}", l.outputs, l.inputs));
            }
            if i > 0 && self.layers[i - 1].outputs != l.inputs {
                return Err(format!("layer {i} takes {} inputs but layer {} gives {}", l.inputs, i - 1, self.layers[i - 1].outputs));
            }
            if !l.weight.iter().chain(&l.bias).all(|x| x.is_finite()) {
                return Err(format!("layer {i} has non-finite weights"));
            }
        }
        Ok(())
    }

    /// Evaluates one row. `scratch` must hold `2 * max_width()` floats; no
    /// allocation happens here so the renderer can call it per ray.
    pub fn forward_into(&self, input: &[f32], output: &mut [f32], scratch: &mut [f32]) {
        let w = self.max_width();
        let (a, b) = scratch.split_at_mut(w);
        a[..input.len()].copy_from_slice(input);
        let (mut cur, mut next) = (a, b);
        let last = self.layers.len() - 1;
        for (li, l) in self.layers.iter().enumerate() {
            let rows = l.weight.chunks_exact(l.inputs);
            for ((n, row), &bias) in next[..l.outputs].iter_mut().zip(rows).zip(&l.bias) {
                let mut acc = bias;
                for (wi, xi) in row.iter().zip(&cur[..l.inputs]) {
                    acc += wi * xi;
                }
                *n = if li < last { acc.max(0.0) } else { acc };
            }
            std::mem::swap(&mut cur, &mut next);
        }
        output.copy_from_slice(&cur[..self.outputs()]);
    }

    /// Evaluates `rows` rows stored contiguously.
    pub fn forward_batch(&self, input: &[f32], output: &mut [f32]) {
        let (ni, no) = (self.inputs(), self.outputs());
        let mut scratch = vec![0.0; 2 * self.max_width()];
        for (x, y) in input.chunks_exact(ni).zip(output.chunks_exact_mut(no)) {
            self.forward_into(x, y, &mut scratch);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn forward_matches_hand_computation() {
        let mlp = Mlp {
            layers: vec![
                Dense { inputs: 2, outputs: 2, weight: vec![1.0, -1.0, 0.5, 0.5], bias: vec![0.0, -1.0] },
                Dense { inputs: 2, outputs: 1, weight: vec![2.0, 3.0], bias: vec![0.25] },
            ],
        };
        mlp.validate().unwrap();
        let mut out = [0.0];
        let mut scratch = vec![0.0; 2 * mlp.max_width()];
        mlp.forward_into(&[3.0, 1.0], &mut out, &mut scratch);
        // hidden = relu([2, 1]) ; out = 2*2 + 3*1 + 0.25
        assert_eq!(out[0], 7.25);
        mlp.forward_into(&[-3.0, 1.0], &mut out, &mut scratch);
        // hidden = relu([-4, -2]) = 0 ; out = 0.25
        assert_eq!(out[0], 0.25);
    }
}
