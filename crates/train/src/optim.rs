//! AdamW, warm-up schedule and gradient clipping, op for op as PyTorch 2.11 does them on CPU
//! (`torch/optim/adam.py::_single_tensor_adam` with decoupled weight decay, `LambdaLR`,
//! `torch/nn/utils/clip_grad.py`), so that a training step matches the reference bitwise.
//!
//! Written here rather than using `tch::nn::Optimizer` because (a) its state (moments, step) cannot
//! be saved, which resumable runs need, and (b) libtorch's C++ AdamW orders its float ops
//! differently from the Python one the reference runs.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use tch::{nn::VarStore, Kind, Tensor};

/// AdamW settings. Defaults are the reference's (`torch.optim.AdamW(lr=1e-4, weight_decay=1e-4)`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdamWConfig {
    /// Peak learning rate, reached at the end of warm-up.
    pub learning_rate: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Decoupled weight decay, applied (as in the reference) to every parameter that has a
    /// gradient, LayerNorm weights, biases and embeddings included.
    pub weight_decay: f64,
    /// Linear warm-up length in steps: lr(n) = learning_rate * min((n + 1) / warmup_steps, 1).
    pub warmup_steps: u64,
    /// Global L2 gradient-norm clipping threshold.
    pub grad_clip_norm: f64,
}

impl Default for AdamWConfig {
    fn default() -> Self {
        Self {
            learning_rate: 1e-4,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 1e-4,
            warmup_steps: 10_000,
            grad_clip_norm: 0.25,
        }
    }
}

impl AdamWConfig {
    /// The learning rate of gradient step `n` (0-based): PyTorch's `LambdaLR` with
    /// `lambda s: min((s + 1) / warmup_steps, 1)`, stepped once per gradient step.
    pub fn lr_at(&self, n: u64) -> f64 {
        let warm = self.warmup_steps.max(1) as f64;
        self.learning_rate * f64::min((n + 1) as f64 / warm, 1.0)
    }
}

/// Per-parameter AdamW state, created the first time the parameter has a gradient (as PyTorch does).
#[derive(Debug)]
pub struct ParamState {
    pub step: u64,
    pub exp_avg: Tensor,
    pub exp_avg_sq: Tensor,
}

/// AdamW over the trainable variables of a `VarStore`, keyed by their state_dict names.
#[derive(Debug)]
pub struct AdamW {
    pub cfg: AdamWConfig,
    params: Vec<(String, Tensor)>,
    pub state: BTreeMap<String, ParamState>,
}

impl AdamW {
    pub fn new(vs: &VarStore, cfg: AdamWConfig) -> Self {
        let mut params: Vec<(String, Tensor)> =
            vs.variables().into_iter().filter(|(_, t)| t.requires_grad()).collect();
        params.sort_by(|a, b| a.0.cmp(&b.0));
        Self { cfg, params, state: BTreeMap::new() }
    }

    /// Zeroes the gradients that exist. Parameters that never received a gradient keep none, so they
    /// stay excluded from clipping and from the update, like PyTorch's `grad is None`.
    pub fn zero_grad(&mut self) {
        for (_, p) in &mut self.params {
            p.zero_grad();
        }
    }

    fn grads(&self) -> Vec<Tensor> {
        self.params.iter().map(|(_, p)| p.grad()).filter(Tensor::defined).collect()
    }

    /// `torch.nn.utils.clip_grad_norm_(params, max_norm)`: scales all gradients in place by
    /// `min(max_norm / (total_norm + 1e-6), 1)` and returns the total norm before clipping.
    pub fn clip_grad_norm(&mut self, max_norm: f64) -> f64 {
        let mut grads = self.grads();
        if grads.is_empty() {
            return 0.0;
        }
        let norms: Vec<Tensor> =
            grads.iter().map(|g| g.linalg_vector_norm(2.0, None::<&[i64]>, false, None::<Kind>)).collect();
        let total = Tensor::stack(&norms, 0).linalg_vector_norm(2.0, None::<&[i64]>, false, None::<Kind>);
        // Python evaluates `max_norm / (total + 1e-6)` as `(total + 1e-6).reciprocal() * max_norm`.
        let coef = ((&total + 1e-6).reciprocal() * max_norm).clamp_max(1.0);
        tch::no_grad(|| {
            for g in &mut grads {
                let _ = g.mul_(&coef);
            }
        });
        total.double_value(&[])
    }

    /// One AdamW update at learning rate `lr`, for every parameter that has a gradient.
    pub fn step(&mut self, lr: f64) {
        let (b1, b2, eps, wd) = (self.cfg.beta1, self.cfg.beta2, self.cfg.eps, self.cfg.weight_decay);
        tch::no_grad(|| {
            for (name, p) in &mut self.params {
                let grad = p.grad();
                if !grad.defined() {
                    continue;
                }
                let st = self.state.entry(name.clone()).or_insert_with(|| ParamState {
                    step: 0,
                    exp_avg: p.zeros_like(),
                    exp_avg_sq: p.zeros_like(),
                });
                st.step += 1;
                let _ = p.mul_(1.0 - lr * wd);
                let _ = st.exp_avg.lerp_(&grad, 1.0 - b1);
                // `addcmul_(g, g, value=v)` computes self + (v * g) * g; tch's addcmul_ has no
                // `value`, and (v * g) with value 1 gives the same bits.
                let _ = st.exp_avg_sq.mul_(b2).addcmul_(&(&grad * (1.0 - b2)), &grad);
                let step = st.step as f64;
                let bias_correction1 = 1.0 - b1.powf(step);
                let bias_correction2 = 1.0 - b2.powf(step);
                let step_size = lr / bias_correction1;
                let bias_correction2_sqrt = bias_correction2.powf(0.5);
                let denom = (st.exp_avg_sq.sqrt() / bias_correction2_sqrt) + eps;
                // `addcdiv_(m, denom, value=-step_size)` is self + (value * m) / denom; same trick.
                let _ = p.addcdiv_(&(&st.exp_avg * -step_size), &denom);
            }
        });
    }

    /// Names of the optimised parameters, sorted.
    pub fn param_names(&self) -> impl Iterator<Item = &str> {
        self.params.iter().map(|(n, _)| n.as_str())
    }
}
