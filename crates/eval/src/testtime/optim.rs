//! The adaptation optimiser: what steps an adaptation's tensors (a soft prompt's tokens, LoRA's
//! adapters, or in full fine-tuning the model's weights, which the evaluation restores after each
//! task). A run's weights are trained by `pdt-train`'s AdamW; MT-BC-Finetune's fine-tuning, which
//! changes a copy of them, uses that one.

use tch::Tensor;

/// Adam (Kingma & Ba) over a few tensors, written out: the adapted tensors live outside any
/// `VarStore`, and their gradients come from `run_backward`.
pub(super) struct Adam {
    lr: f64,
    t: i32,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
}

impl Adam {
    const B1: f64 = 0.9;
    const B2: f64 = 0.999;
    const EPS: f64 = 1e-8;

    pub(super) fn new(params: &[&Tensor], lr: f64) -> Self {
        let zeros = || params.iter().map(|p| p.zeros_like()).collect();
        Self { lr, t: 0, m: zeros(), v: zeros() }
    }

    pub(super) fn step(&mut self, params: &[&Tensor], grads: &[Tensor]) {
        self.t += 1;
        let (c1, c2) = (1.0 - Self::B1.powi(self.t), 1.0 - Self::B2.powi(self.t));
        tch::no_grad(|| {
            for (i, (p, g)) in params.iter().zip(grads).enumerate() {
                // A tensor the loss does not reach has no gradient (in full fine-tuning, the
                // heads kept only for the reference's weights): left as it is, as PyTorch's Adam
                // leaves a parameter whose grad is None.
                if !g.defined() {
                    continue;
                }
                self.m[i] = &self.m[i] * Self::B1 + g * (1.0 - Self::B1);
                self.v[i] = &self.v[i] * Self::B2 + g.square() * (1.0 - Self::B2);
                let update = (&self.m[i] / c1) / ((&self.v[i] / c2).sqrt() + Self::EPS) * self.lr;
                let _ = p.shallow_clone().f_sub_(&update);
            }
        });
    }
}
