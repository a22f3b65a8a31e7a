//! LoRA adapters on the attention projections (Hu et al. 2021): `W x + b + (alpha / r) B A x`,
//! held apart from the model's weights, so the frozen backbone is never written and one model
//! serves any number of adapter sets (one per test task).
//!
//! HF's `Conv1D` computes `x @ W` with `W` stored `(in, out)`; the delta is written the same way,
//! `x @ A @ B` with `A (in, r)`, `B (r, out)`. `B` starts at zero, so an adapter set at step 0
//! leaves every output as the frozen model's (`tests/lora.rs`).

use crate::config::PromptDtConfig;
use tch::{Device, Kind, Tensor};

/// One low-rank delta of a projection.
#[derive(Debug)]
pub struct LoraPair {
    /// `[in, r]`
    pub a: Tensor,
    /// `[r, out]`
    pub b: Tensor,
    /// `alpha / r`.
    pub scale: f64,
}

impl LoraPair {
    /// `x @ A @ B * scale`, `[.., out]` for `x` `[.., in]`.
    pub fn delta(&self, x: &Tensor) -> Tensor {
        x.matmul(&self.a).matmul(&self.b) * self.scale
    }
}

/// The adapters of one transformer block: on `attn.c_attn`, and optionally on `attn.c_proj`.
#[derive(Debug)]
pub struct LoraLayer {
    pub c_attn: LoraPair,
    pub c_proj: Option<LoraPair>,
}

/// One adapter set: a [`LoraLayer`] per transformer block, in block order.
#[derive(Debug)]
pub struct LoraAdapters {
    pub layers: Vec<LoraLayer>,
}

/// Shape and scale of an adapter set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoraShape {
    /// Rank r (at least 1).
    pub rank: usize,
    /// alpha: the delta is scaled by alpha / r.
    pub alpha: f64,
    /// Also adapt `attn.c_proj` (`c_attn` always is).
    pub c_proj: bool,
}

impl LoraAdapters {
    /// A fresh adapter set for a model of `cfg`: every `A` from `a_init` (called once per matrix
    /// with its element count, returning that many values), every `B` zero. `A` values are the
    /// caller's so that they come from its seed streams, not from libtorch's generator. The
    /// tensors require gradients.
    pub fn new(
        cfg: &PromptDtConfig,
        shape: LoraShape,
        mut a_init: impl FnMut(usize) -> Vec<f32>,
        device: Device,
    ) -> Self {
        let (h, r) = (cfg.hidden_size as i64, shape.rank as i64);
        let scale = shape.alpha / shape.rank as f64;
        let mut pair = |n_in: i64, n_out: i64| {
            let values = a_init((n_in * r) as usize);
            let a = Tensor::from_slice(&values).view([n_in, r]).to_device(device);
            let b = Tensor::zeros([r, n_out], (Kind::Float, device));
            LoraPair { a: a.set_requires_grad(true), b: b.set_requires_grad(true), scale }
        };
        let layers = (0..cfg.n_layer)
            .map(|_| LoraLayer { c_attn: pair(h, 3 * h), c_proj: shape.c_proj.then(|| pair(h, h)) })
            .collect();
        Self { layers }
    }

    /// Every trainable tensor, in a fixed order (block, then `c_attn` A, B, then `c_proj` A, B).
    pub fn parameters(&self) -> Vec<&Tensor> {
        let mut out = Vec::new();
        for l in &self.layers {
            out.extend([&l.c_attn.a, &l.c_attn.b]);
            if let Some(p) = &l.c_proj {
                out.extend([&p.a, &p.b]);
            }
        }
        out
    }

    /// The same adapters (tensors shared, not copied): a second holder of a trained set, which
    /// nothing writes any more.
    pub fn shallow_clone(&self) -> Self {
        let pair = |p: &LoraPair| LoraPair {
            a: p.a.shallow_clone(),
            b: p.b.shallow_clone(),
            scale: p.scale,
        };
        let layers = self
            .layers
            .iter()
            .map(|l| LoraLayer { c_attn: pair(&l.c_attn), c_proj: l.c_proj.as_ref().map(pair) })
            .collect();
        Self { layers }
    }

    /// Number of trainable values.
    pub fn numel(&self) -> usize {
        self.parameters().iter().map(|t| t.numel()).sum()
    }
}
