//! AdamW, warm-up schedule and gradient clipping, op for op as PyTorch 2.11 does them on CPU
//! (`torch/optim/adam.py::_single_tensor_adam` with decoupled weight decay, `LambdaLR`,
//! `torch/nn/utils/clip_grad.py`), so that a training step matches the reference bitwise.
//!
//! Written here rather than using `tch::nn::Optimizer` because (a) its state (moments, step) cannot
//! be saved, which resumable runs need, and (b) libtorch's C++ AdamW orders its float ops
//! differently from the Python one the reference runs.

use pdt_rundir::config::AdamWConfig;
use std::collections::BTreeMap;
use tch::{nn::VarStore, Tensor};

/// Per-parameter AdamW state, created the first time the parameter has a gradient (as PyTorch does).
#[derive(Debug)]
pub struct ParamState {
    pub step: u64,
    pub exp_avg: Tensor,
    pub exp_avg_sq: Tensor,
}

/// Gradients of the optimised parameters, in the optimiser's parameter order.
#[derive(Debug)]
pub struct Grads(pub Vec<Option<Tensor>>);

/// AdamW over the trainable variables of a `VarStore`, keyed by their state_dict names.
#[derive(Debug)]
pub struct AdamW {
    pub cfg: AdamWConfig,
    pub(super) params: Vec<(String, Tensor)>,
    pub state: BTreeMap<String, ParamState>,
}

impl AdamW {
    /// Optimises the variables of `vs` named in `order` (PyTorch's `model.parameters()` order,
    /// which clipping depends on: see `PromptDtConfig::parameter_names`). Variables of `vs` missing
    /// from `order` are appended in name order.
    pub fn new(vs: &VarStore, order: &[String], cfg: AdamWConfig) -> Self {
        Self { cfg, params: optimised_params(vs, order), state: BTreeMap::new() }
    }

    /// Gradients of `loss` with respect to every optimised parameter, as fresh tensors.
    ///
    /// Parameters that do not influence the loss get no gradient (`None`) and are then left out of
    /// clipping and of the update, exactly as PyTorch's `grad is None` (the unused prediction heads,
    /// `wte`, and the prompt layers of a no-prompt variant). Nothing accumulates in `.grad`: PyTorch's
    /// `zero_grad(set_to_none=True)` followed by `backward()` gives the same fresh tensors.
    pub fn backward(&self, loss: &Tensor) -> Grads {
        let inputs: Vec<&Tensor> = self.params.iter().map(|(_, p)| p).collect();
        let grads = Tensor::run_backward(&[loss], &inputs, false, false);
        Grads(grads.into_iter().map(|g| g.defined().then_some(g)).collect())
    }

    /// `torch.nn.utils.clip_grad_norm_(params, max_norm)`: scales all gradients in place by
    /// `min(max_norm / (total_norm + 1e-6), 1)` and returns the total norm before clipping, a 0-d
    /// tensor on the gradients' device, not read (as PyTorch's: reading waits for the device).
    /// With no gradient at all, a 0-d zero on the CPU.
    pub fn clip_grad_norm(&self, grads: &mut Grads, max_norm: f64) -> Tensor {
        let present: Vec<&mut Tensor> = grads.0.iter_mut().flatten().collect();
        if present.is_empty() {
            return Tensor::from(0f32);
        }
        // `norm()` is at::norm(p=2), which libtorch computes with linalg_vector_norm's kernel (tch
        // 0.24 has no binding for the latter).
        let norms: Vec<Tensor> = present.iter().map(|g| g.norm()).collect();
        let total = Tensor::stack(&norms, 0).norm();
        // Python evaluates `max_norm / (total + 1e-6)` as `(total + 1e-6).reciprocal() * max_norm`.
        let coef = ((&total + 1e-6).reciprocal() * max_norm).clamp_max(1.0);
        for g in present {
            let _ = g.g_mul_(&coef);
        }
        total
    }

    /// One AdamW update at learning rate `lr`, for every parameter that has a gradient.
    pub fn step(&mut self, grads: &Grads, lr: f64) {
        tch::no_grad(|| {
            for ((name, p), grad) in self.params.iter_mut().zip(&grads.0) {
                let Some(grad) = grad else { continue };
                let st = self.state.entry(name.clone()).or_insert_with(|| ParamState {
                    step: 0,
                    exp_avg: p.zeros_like(),
                    exp_avg_sq: p.zeros_like(),
                });
                st.step += 1;
                let moments = Moments { exp_avg: &mut st.exp_avg, exp_avg_sq: &mut st.exp_avg_sq };
                adamw_update(p, moments, grad, st.step, lr, &self.cfg);
            }
        });
    }

    /// Names of the optimised parameters, in optimisation order.
    pub fn param_names(&self) -> impl Iterator<Item = &str> {
        self.params.iter().map(|(n, _)| n.as_str())
    }
}

/// The trainable variables of `vs`: those named in `order` first, in that order, then the others
/// in name order.
pub(crate) fn optimised_params(vs: &VarStore, order: &[String]) -> Vec<(String, Tensor)> {
    let mut vars = vs.variables();
    let mut params: Vec<(String, Tensor)> =
        order.iter().filter_map(|n| vars.remove(n).map(|t| (n.clone(), t))).collect();
    let mut rest: Vec<(String, Tensor)> = vars.into_iter().collect();
    rest.sort_by(|a, b| a.0.cmp(&b.0));
    params.extend(rest);
    params.retain(|(_, t)| t.requires_grad());
    params
}

/// The two Adam moments of one tensor (or of one flat buffer), updated in place.
pub(crate) struct Moments<'a> {
    pub(crate) exp_avg: &'a mut Tensor,
    pub(crate) exp_avg_sq: &'a mut Tensor,
}

/// PyTorch's `_single_tensor_adam` body (decoupled weight decay) for one tensor `p` whose `step`
/// (1-based, already incremented) is given; element-wise only, so `FlatAdamW` runs the same ops
/// on a whole flat buffer. Call under `no_grad`.
pub(crate) fn adamw_update(
    p: &mut Tensor,
    m: Moments<'_>,
    grad: &Tensor,
    step: u64,
    lr: f64,
    cfg: &AdamWConfig,
) {
    let (b1, b2, eps, wd) = (cfg.beta1, cfg.beta2, cfg.eps, cfg.weight_decay);
    let _ = p.g_mul_scalar_(1.0 - lr * wd);
    let _ = m.exp_avg.lerp_(grad, 1.0 - b1);
    // `addcmul_(g, g, value=v)` computes self + (v * g) * g; tch's addcmul_ has no `value`, and
    // (v * g) with value 1 gives the same bits.
    let _ = m.exp_avg_sq.g_mul_scalar_(b2).addcmul_(&(grad * (1.0 - b2)), grad);
    let step = step as f64;
    let bias_correction1 = 1.0 - b1.powf(step);
    let bias_correction2 = 1.0 - b2.powf(step);
    let step_size = lr / bias_correction1;
    let bias_correction2_sqrt = bias_correction2.powf(0.5);
    let denom = (m.exp_avg_sq.sqrt() / bias_correction2_sqrt) + eps;
    // `addcdiv_(m, denom, value=-step_size)` is self + (value * m) / denom; same trick.
    let _ = p.addcdiv_(&(&*m.exp_avg * -step_size), &denom);
}
