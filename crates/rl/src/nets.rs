//! The networks of SAC and TD3: plain ReLU MLPs whose parameters live in **one flat tensor**.
//!
//! Every weight and bias is a view into the flat vector, so an optimiser step, a target-network
//! update or a checkpoint is a handful of ops on one tensor instead of a loop over layers (the
//! update loop is small-matrix work where per-op overhead matters). An ensemble of `E` identical
//! MLPs (the twin critics) shares one flat vector and runs as batched matmuls: one `baddbmm` per
//! layer for both critics.
//!
//! Layout of member `e`, layer `l` (fan-in `i`, fan-out `o`): the weight is stored `[E, i, o]`
//! (input-major, i.e. the transpose of PyTorch's `nn.Linear.weight`), then the bias `[E, 1, o]`.
//! Initialisation is PyTorch's `nn.Linear` default: both U(-1/sqrt(i), 1/sqrt(i)).

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};

/// Where one layer's weight and bias sit in the flat vector.
#[derive(Debug, Clone, Copy)]
struct Layer {
    w_off: i64,
    b_off: i64,
    fan_in: i64,
    fan_out: i64,
}

/// `E` ReLU MLPs of the same sizes (`sizes = [in, h1, ..., out]`), no activation on the output.
#[derive(Debug)]
pub struct Mlp {
    /// `[num_params]`, a leaf that requires grad.
    pub flat: Tensor,
    layers: Vec<Layer>,
    members: i64,
    sizes: Vec<i64>,
}

impl Mlp {
    /// Number of parameters of `members` MLPs of `sizes`.
    pub fn num_params(sizes: &[i64], members: i64) -> i64 {
        sizes.windows(2).map(|w| members * (w[0] * w[1] + w[1])).sum()
    }

    /// A freshly initialised ensemble; all randomness from `rng`.
    pub fn new(sizes: &[i64], members: i64, rng: &mut ChaCha8Rng, device: Device) -> Self {
        let mut values = Vec::with_capacity(Self::num_params(sizes, members) as usize);
        let mut layers = Vec::with_capacity(sizes.len().saturating_sub(1));
        for w in sizes.windows(2) {
            let (fan_in, fan_out) = (w[0], w[1]);
            let bound = 1.0 / (fan_in as f32).sqrt();
            let w_off = values.len() as i64;
            for _ in 0..members * fan_in * fan_out {
                values.push(rng.random_range(-bound..bound));
            }
            let b_off = values.len() as i64;
            for _ in 0..members * fan_out {
                values.push(rng.random_range(-bound..bound));
            }
            layers.push(Layer { w_off, b_off, fan_in, fan_out });
        }
        let flat = Tensor::from_slice(&values).to_device(device).set_requires_grad(true);
        Self { flat, layers, members, sizes: sizes.to_vec() }
    }

    /// A copy with its own storage (for target networks), not requiring grad.
    pub fn detached_copy(&self) -> Self {
        let flat = self.flat.detach().copy();
        Self { flat, layers: self.layers.clone(), members: self.members, sizes: self.sizes.clone() }
    }

    pub fn sizes(&self) -> &[i64] {
        &self.sizes
    }

    pub fn members(&self) -> i64 {
        self.members
    }

    fn weight(&self, l: &Layer) -> Tensor {
        let n = self.members * l.fan_in * l.fan_out;
        self.flat.narrow(0, l.w_off, n).view([self.members, l.fan_in, l.fan_out])
    }

    fn bias(&self, l: &Layer) -> Tensor {
        self.flat.narrow(0, l.b_off, self.members * l.fan_out).view([self.members, 1, l.fan_out])
    }

    /// `x`: `[B, in]` (fed to every member) or `[E, B, in]`; returns `[E, B, out]`.
    ///
    /// Each member runs as its own chain of `addmm`s: on CPU, libtorch's 2-D matmul (and its
    /// backward) is markedly faster at these sizes than one batched `baddbmm` over the members.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let last = self.layers.len().saturating_sub(1);
        let outs: Vec<Tensor> = (0..self.members)
            .map(|e| {
                let mut h = if x.dim() == 2 { x.shallow_clone() } else { x.get(e) }; // [B, in]
                for (i, l) in self.layers.iter().enumerate() {
                    let w = self.weight(l).get(e); // [in, out]
                    let b = self.bias(l).get(e).squeeze_dim(0); // [out]
                    h = b.addmm(&h, &w); // [B, out]
                    if i < last {
                        h = h.relu();
                    }
                }
                h
            })
            .collect();
        Tensor::stack(&outs, 0) // [E, B, out]
    }

    /// Target-network update `target <- (1 - tau) * target + tau * self` (Polyak averaging).
    pub fn soft_update_into(&self, target: &mut Mlp, tau: f64) {
        tch::no_grad(|| {
            let _ = target.flat.lerp_(&self.flat, tau);
        });
    }

    /// The parameters as host floats (checkpoints).
    pub fn to_vec(&self) -> Vec<f32> {
        tensor_to_vec(&self.flat)
    }

    /// Overwrites the parameters from host floats; errors on a length mismatch.
    pub fn load_vec(&mut self, values: &[f32]) -> Result<(), String> {
        let n = self.flat.numel();
        if values.len() != n {
            return Err(format!("{} values for a network of {n} parameters", values.len()));
        }
        tch::no_grad(|| {
            let src = Tensor::from_slice(values).to_device(self.flat.device());
            self.flat.copy_(&src);
        });
        Ok(())
    }

    /// Named views of the parameters (`layers.{l}.weight` `[E, in, out]`, `layers.{l}.bias`
    /// `[E, 1, out]`), for exporting readable weight files.
    pub fn named_shapes(&self) -> Vec<(String, i64, Vec<i64>)> {
        let mut out = Vec::new();
        for (i, l) in self.layers.iter().enumerate() {
            out.push((
                format!("layers.{i}.weight"),
                l.w_off,
                vec![self.members, l.fan_in, l.fan_out],
            ));
            out.push((format!("layers.{i}.bias"), l.b_off, vec![self.members, 1, l.fan_out]));
        }
        out
    }
}

/// Layer sizes `[input, hidden.., output]` of an MLP.
pub fn mlp_sizes(input: i64, hidden: &[i64], output: i64) -> Vec<i64> {
    let mut s = vec![input];
    s.extend_from_slice(hidden);
    s.push(output);
    s
}

/// Adam (no weight decay) on one flat parameter tensor, with the same float ops as
/// `torch.optim.Adam`'s single-tensor path. Its state is two tensors and a step count, so it can be
/// checkpointed exactly.
#[derive(Debug)]
pub struct Adam {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub step: u64,
    pub exp_avg: Tensor,
    pub exp_avg_sq: Tensor,
}

impl Adam {
    pub fn new(param: &Tensor, lr: f64) -> Self {
        let zeros = param.detach().zeros_like();
        Self {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            step: 0,
            exp_avg: zeros.copy(),
            exp_avg_sq: zeros,
        }
    }

    /// One update of `param` with gradient `grad`.
    pub fn update(&mut self, param: &mut Tensor, grad: &Tensor) {
        let (b1, b2) = (self.beta1, self.beta2);
        tch::no_grad(|| {
            self.step += 1;
            let _ = self.exp_avg.lerp_(grad, 1.0 - b1);
            let _ = self.exp_avg_sq.g_mul_scalar_(b2).addcmul_(&(grad * (1.0 - b2)), grad);
            let step = self.step as f64;
            let step_size = self.lr / (1.0 - b1.powf(step));
            let bias_correction2_sqrt = (1.0 - b2.powf(step)).sqrt();
            let denom = (self.exp_avg_sq.sqrt() / bias_correction2_sqrt) + self.eps;
            let _ = param.addcdiv_(&(&self.exp_avg * -step_size), &denom);
        });
    }

    /// `(exp_avg, exp_avg_sq)` as host floats.
    pub fn state_vecs(&self) -> (Vec<f32>, Vec<f32>) {
        (tensor_to_vec(&self.exp_avg), tensor_to_vec(&self.exp_avg_sq))
    }

    /// Restores the moments and the step count; errors on a length mismatch.
    pub fn load_state(
        &mut self,
        step: u64,
        exp_avg: &[f32],
        exp_avg_sq: &[f32],
    ) -> Result<(), String> {
        let n = self.exp_avg.numel();
        if exp_avg.len() != n || exp_avg_sq.len() != n {
            return Err(format!(
                "optimiser moments of {}/{} values for {n} parameters",
                exp_avg.len(),
                exp_avg_sq.len()
            ));
        }
        let dev = self.exp_avg.device();
        self.exp_avg = Tensor::from_slice(exp_avg).to_device(dev);
        self.exp_avg_sq = Tensor::from_slice(exp_avg_sq).to_device(dev);
        self.step = step;
        Ok(())
    }
}

/// The gradient of `loss` with respect to `param` alone (nothing accumulates anywhere else).
pub fn grad_of(loss: &Tensor, param: &Tensor) -> Tensor {
    let mut g = Tensor::run_backward(&[loss], &[param], false, false);
    g.pop().unwrap_or_else(|| param.zeros_like())
}

/// A tensor's values as host `f32`s.
pub fn tensor_to_vec(t: &Tensor) -> Vec<f32> {
    let t = t.detach().to_kind(Kind::Float).to_device(Device::Cpu).contiguous().view([-1]);
    let n = t.numel();
    let mut v = vec![0f32; n];
    t.copy_data(&mut v, n);
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn ensemble_members_equal_separate_mlps() {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let net = Mlp::new(&[3, 8, 2], 2, &mut rng, Device::Cpu);
        assert_eq!(net.flat.numel() as i64, Mlp::num_params(&[3, 8, 2], 2));
        let x = Tensor::from_slice(&[0.1f32, -0.2, 0.3, 1.0, 0.5, -0.5]).view([2, 3]);
        let y = net.forward(&x); // [2, 2, 2]
        assert_eq!(y.size(), vec![2, 2, 2]);
        // Member 1 by hand: relu(x W0 + b0) W1 + b1.
        let l0 = net.layers[0];
        let l1 = net.layers[1];
        let w0 = net.weight(&l0).get(1);
        let b0 = net.bias(&l0).get(1);
        let w1 = net.weight(&l1).get(1);
        let b1 = net.bias(&l1).get(1);
        let want = (x.matmul(&w0) + b0).relu().matmul(&w1) + b1;
        let diff = (y.get(1) - want).abs().max().double_value(&[]);
        assert!(diff < 1e-6, "{diff}");
    }

    #[test]
    fn init_is_seeded_and_bounded() {
        let a = Mlp::new(&[4, 16, 1], 1, &mut ChaCha8Rng::seed_from_u64(7), Device::Cpu).to_vec();
        let b = Mlp::new(&[4, 16, 1], 1, &mut ChaCha8Rng::seed_from_u64(7), Device::Cpu).to_vec();
        let c = Mlp::new(&[4, 16, 1], 1, &mut ChaCha8Rng::seed_from_u64(8), Device::Cpu).to_vec();
        assert_eq!(a, b);
        assert_ne!(a, c);
        // First layer bound 1/sqrt(4) = 0.5, second 1/sqrt(16) = 0.25.
        assert!(a[..80].iter().all(|v| v.abs() < 0.5));
        assert!(a[80..].iter().all(|v| v.abs() < 0.25));
    }

    #[test]
    fn adam_minimises_a_quadratic_and_soft_update_interpolates() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut net = Mlp::new(&[2, 1], 1, &mut rng, Device::Cpu);
        let mut opt = Adam::new(&net.flat, 0.05);
        for _ in 0..400 {
            let loss = (&net.flat - 3.0).square().sum(Kind::Float);
            let g = grad_of(&loss, &net.flat);
            opt.update(&mut net.flat, &g);
        }
        assert!(net.to_vec().iter().all(|v| (v - 3.0).abs() < 1e-2), "{:?}", net.to_vec());
        let mut target = Mlp::new(&[2, 1], 1, &mut rng, Device::Cpu).detached_copy();
        target.load_vec(&[0.0, 0.0, 0.0]).expect("3 params");
        net.soft_update_into(&mut target, 0.25);
        let t = target.to_vec();
        let n = net.to_vec();
        for (a, b) in t.iter().zip(&n) {
            assert!((a - 0.25 * b).abs() < 1e-6);
        }
    }
}
