//! MACAW (Mitchell et al., ICML 2021): MAML over a value function V_phi(s) and an
//! advantage-weighted policy pi_theta(a|s), neither told the task. One SGD step with learned
//! per-tensor learning rates adapts both to a task's offline data; the outer losses are evaluated
//! with the adapted parameters and their gradients flow back through that step (second order).
//!
//! Written from `../shared/reference/macaw.md` (the official code at commit 3dfd4f9 pinned down line
//! by line; its section numbers are cited below as "spec 4" etc.). Parameters are explicit tensors,
//! so the inner step is `p - softplus(rho) * grad(loss, p, create_graph)`: no `higher`, no modules.
//! The PyTorch twin of this file is `scripts/golden/macaw_torch.py`: the same ops in the same order,
//! which the parity test (`tests/it/parity.rs`) checks bit for bit on one CPU thread.
//!
//! Deliberate differences from the official code are marked `DIFFERENCE` where they live and listed
//! in `docs/macaw.md`.

pub mod bench;
pub mod buffer;
pub mod rollout;

pub use buffer::{Batch, BufferSpec, TaskBuffer};

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

/// The weight transform's latent size, hard-coded to 100 in the official `nn.py`.
pub const LATENT: i64 = 100;
/// Hidden width of the advantage head (`policy_head = [32, 1]`).
pub const HEAD: i64 = 32;

#[derive(Debug, thiserror::Error)]
pub enum MacawError {
    #[error("task {task}: {message}")]
    Data { task: String, message: String },
    #[error("invalid MACAW configuration: {0}")]
    Config(String),
    #[error("checkpoint {path}: {message}")]
    Checkpoint { path: String, message: String },
    #[error(transparent)]
    Env(#[from] pdt_envs::EnvError),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
}

// The hyper-parameters are part of a run's configuration (`[macaw]` of config.toml), which is read
// without libtorch, so they are defined in `pdt_rundir`.
use pdt_rundir::config::macaw::{Activation, AdaptOrder, InvalidMacaw, MacawConfig};

impl From<InvalidMacaw> for MacawError {
    fn from(e: InvalidMacaw) -> Self {
        MacawError::Config(e.0)
    }
}

/// The buffer's settings in a configuration (a function here, not a method: the configuration is
/// `pdt_rundir`'s, read without libtorch).
pub fn buffer_spec(cfg: &MacawConfig) -> BufferSpec {
    BufferSpec {
        rows: cfg.buffer_rows,
        skip: cfg.buffer_skip,
        reverse_episodes: cfg.reverse_episodes,
        discount: cfg.discount,
    }
}

/// Layer shapes `(in, out)` of both networks (spec 3.3).
#[derive(Debug, Clone, PartialEq)]
pub struct Dims {
    pub obs: i64,
    pub act: i64,
    /// fc_0 .. fc_depth: [O, W, .., W, 1].
    pub value: Vec<(i64, i64)>,
    /// fc_0 .. fc_depth ([O, W, .., W, A]), then head_0 (W + A -> 32) and head_1 (32 -> 1).
    pub policy: Vec<(i64, i64)>,
}

impl Dims {
    pub fn new(obs: usize, act: usize, width: usize, depth: usize) -> Self {
        let (o, a, w) = (obs as i64, act as i64, width as i64);
        let mut trunk = vec![o];
        trunk.extend(std::iter::repeat_n(w, depth));
        let layers = |last: i64| -> Vec<(i64, i64)> {
            trunk.iter().copied().zip(trunk[1..].iter().copied().chain([last])).collect()
        };
        let value = layers(1);
        let mut policy = layers(a);
        policy.extend([(w + a, HEAD), (HEAD, 1)]);
        Self { obs: o, act: a, value, policy }
    }

    /// Parameter names in the official order: per layer `z`, `weight` (the generator's, aliased
    /// `fc.weight`), `bias`.
    pub fn names(&self) -> (Vec<String>, Vec<String>) {
        let names = |net: &str, layers: usize, head: bool| -> Vec<String> {
            (0..layers)
                .flat_map(|i| {
                    let tag = if head && i >= layers - 2 {
                        format!("head_{}", i - (layers - 2))
                    } else {
                        format!("fc_{i}")
                    };
                    ["z", "weight", "bias"].map(|p| format!("{net}.{tag}.{p}"))
                })
                .collect()
        };
        (names("value", self.value.len(), false), names("policy", self.policy.len(), true))
    }
}

/// Every trained tensor of MACAW. All are leaves that require a gradient.
#[derive(Debug)]
pub struct Params {
    /// 3 tensors per layer of `Dims::value`.
    pub value: Vec<Tensor>,
    /// 3 tensors per layer of `Dims::policy` (the head's last).
    pub policy: Vec<Tensor>,
    /// Raw learned inner learning rates, one per value tensor: lr = softplus(rho).
    pub rho_v: Tensor,
    /// One per policy tensor (the head's never get a gradient: spec 5.2).
    pub rho_pi: Tensor,
    /// Raw advantage-head coefficient (0-d): softplus(rho_adv).
    pub rho_adv: Tensor,
}

impl Params {
    /// The official initialisation (spec 3.2): z ~ N(0, (1/out)^2), the generator's weight and bias
    /// U(-0.1, 0.1) (PyTorch's nn.Linear default for fan-in 100, not tch's Kaiming default). Draws
    /// from libtorch's global generator: seed it first (`tch::manual_seed`).
    pub fn init(dims: &Dims, cfg: &MacawConfig, kind: Kind, device: Device) -> Self {
        let opts = (kind, device);
        let bound = 1.0 / (LATENT as f64).sqrt();
        let make = |layers: &[(i64, i64)]| -> Vec<Tensor> {
            layers
                .iter()
                .flat_map(|&(n_in, n_out)| {
                    let rows = n_in * n_out + n_out;
                    let z = Tensor::randn([LATENT], opts) / n_out as f64;
                    let w = (Tensor::rand([rows, LATENT], opts) * 2.0 - 1.0) * bound;
                    let b = (Tensor::rand([rows], opts) * 2.0 - 1.0) * bound;
                    [z, w, b].map(|t| t.set_requires_grad(true))
                })
                .collect()
        };
        let value = make(&dims.value);
        let policy = make(&dims.policy);
        let rho =
            |n: usize, init: f64| Tensor::full([n as i64], init.ln(), opts).set_requires_grad(true);
        Self {
            rho_v: rho(value.len(), cfg.inner_value_lr),
            rho_pi: rho(policy.len(), cfg.inner_policy_lr),
            rho_adv: Tensor::from(cfg.advantage_head_coef.ln())
                .to_kind(kind)
                .to_device(device)
                .set_requires_grad(true),
            value,
            policy,
        }
    }

    /// Every tensor with its name (`value.fc_0.z`, ..., `rho_v`, `rho_pi`, `rho_adv`).
    pub fn named(&self, dims: &Dims) -> Vec<(String, &Tensor)> {
        let (vn, pn) = dims.names();
        let mut out: Vec<(String, &Tensor)> =
            vn.into_iter().zip(&self.value).chain(pn.into_iter().zip(&self.policy)).collect();
        out.push(("rho_v".into(), &self.rho_v));
        out.push(("rho_pi".into(), &self.rho_pi));
        out.push(("rho_adv".into(), &self.rho_adv));
        out
    }

    /// The parameter groups of the outer optimisers, in the official order (spec 5.1 step 4).
    pub fn groups(&self) -> [Vec<&Tensor>; 5] {
        [
            self.value.iter().collect(),
            self.policy.iter().collect(),
            vec![&self.rho_v],
            vec![&self.rho_pi],
            vec![&self.rho_adv],
        ]
    }

    pub fn zero_grad(&mut self) {
        for t in self.value.iter_mut().chain(self.policy.iter_mut()) {
            t.zero_grad();
        }
        self.rho_v.zero_grad();
        self.rho_pi.zero_grad();
        self.rho_adv.zero_grad();
    }

    pub fn count(&self) -> i64 {
        self.value.iter().chain(&self.policy).map(Tensor::numel).sum::<usize>() as i64
    }
}

// ---------------------------------------------------------------- networks (spec 3) ---------

fn activation(x: &Tensor, a: Activation) -> Tensor {
    match a {
        Activation::Relu => x.relu(),
        Activation::Tanh => x.tanh(),
    }
}

/// The weight transform: theta = Wg z + bg, y = x M + b with M = theta[:in*out].view(in, out).
fn wlinear(x: &Tensor, p: &[Tensor], (n_in, n_out): (i64, i64)) -> Tensor {
    let theta = p[0].linear(&p[1], Some(&p[2])); // [in*out + out]
    let m = theta.narrow(0, 0, n_in * n_out).view([n_in, n_out]); // input index major
    x.matmul(&m) + theta.narrow(0, n_in * n_out, n_out)
}

/// V_phi(s): `[B, O]` -> `[B, 1]`.
pub fn value_forward(p: &[Tensor], dims: &Dims, s: &Tensor, act: Activation) -> Tensor {
    let mut x = s.shallow_clone();
    for (i, &d) in dims.value.iter().enumerate() {
        if i > 0 {
            x = activation(&x, act);
        }
        x = wlinear(&x, &p[3 * i..3 * i + 3], d);
    }
    x
}

/// The policy mean mu(s) `[B, A]`, and with dataset actions `a` the advantage head's prediction
/// `[B, 1]`.
pub fn policy_forward(
    p: &[Tensor],
    dims: &Dims,
    s: &Tensor,
    a: Option<&Tensor>,
    act: Activation,
) -> (Tensor, Option<Tensor>) {
    let n_trunk = dims.policy.len() - 2;
    let mut x = s.shallow_clone();
    for i in 0..n_trunk - 1 {
        if i > 0 {
            x = activation(&x, act);
        }
        x = wlinear(&x, &p[3 * i..3 * i + 3], dims.policy[i]);
    }
    let h = x; // pre-activation output of the last hidden layer (official `pre_seq`)
    let j = n_trunk - 1;
    let mu = wlinear(&activation(&h, act), &p[3 * j..3 * j + 3], dims.policy[j]).tanh();
    let head = a.map(|a| {
        // Official quirk: the activation is applied to the concatenation, so negative action
        // components are zeroed (spec 3.3).
        let y = activation(&Tensor::cat(&[&h, a], -1), act);
        let k = n_trunk;
        let y = wlinear(&y, &p[3 * k..3 * k + 3], dims.policy[k]);
        wlinear(&activation(&y, act), &p[3 * k + 3..3 * k + 6], dims.policy[k + 1])
    });
    (mu, head)
}

// ---------------------------------------------------------------- losses (spec 4) -----------

/// Inner (`target` None): mean (V(s) - G)^2. Outer: the target bootstraps at the episode end with
/// the soft target network, G + kappa V_target(s_T).
pub fn value_loss(
    p: &[Tensor],
    dims: &Dims,
    b: &Batch,
    target: Option<&[Tensor]>,
    cfg: &MacawConfig,
) -> Tensor {
    let ret = tch::no_grad(|| match target {
        None => b.mc_return.shallow_clone(),
        Some(t) => {
            &b.mc_return
                + &b.terminal_discount
                    * value_forward(t, dims, &b.terminal_obs, cfg.hidden_activation)
        }
    });
    let v = value_forward(p, dims, &b.obs, cfg.hidden_activation);
    (v - ret).pow_tensor_scalar(2).mean(None::<Kind>)
}

/// The advantages A = G + kappa V(s_T) - V(s) `[B]` (always bootstrapped) and the AWR weights
/// exp(min((A - mean A) / std A / T, ln clip)) `[B]`, without gradient.
pub fn advantages(vp: &[Tensor], dims: &Dims, b: &Batch, cfg: &MacawConfig) -> (Tensor, Tensor) {
    tch::no_grad(|| {
        let act = cfg.hidden_activation;
        let est =
            &b.mc_return + &b.terminal_discount * value_forward(vp, dims, &b.terminal_obs, act);
        let adv = (est - value_forward(vp, dims, &b.obs, act)).squeeze_dim(-1); // [B]
        let norm = (&adv - adv.mean(None::<Kind>)) / adv.std(true) / cfg.adaptation_temp;
        let weights = norm.clamp_max(cfg.exp_advantage_clip.ln()).exp();
        (adv, weights)
    })
}

/// The AWR loss, plus in the inner loss the advantage-regression term softplus(rho_adv) (A_hat - A)^2.
pub fn policy_loss(
    p: &[Tensor],
    dims: &Dims,
    vp: &[Tensor],
    b: &Batch,
    rho_adv: &Tensor,
    inner: bool,
    cfg: &MacawConfig,
) -> Tensor {
    let (adv, weights) = advantages(vp, dims, b, cfg);
    let (mu, pred) =
        policy_forward(p, dims, &b.obs, inner.then_some(&b.act), cfg.hidden_activation);
    // torch.distributions.Normal(mu, sigma).log_prob(a), summed over the action dims.
    let sigma = cfg.action_sigma;
    let var = sigma.powf(2.0);
    let log_prob = (-(&b.act - mu).pow_tensor_scalar(2)) / (2.0 * var)
        - sigma.ln()
        - (2.0 * std::f64::consts::PI).sqrt().ln();
    let awr = -(log_prob.sum_dim_intlist(-1, false, None::<Kind>) * weights);
    // Out of place, as the PyTorch twin (an in-place add would round the same, but keep the graph
    // the same shape as PyTorch's).
    let losses = match pred {
        Some(pred) => awr + rho_adv.softplus() * (pred.squeeze_dim(-1) - adv).pow_tensor_scalar(2),
        None => awr,
    };
    losses.mean(None::<Kind>)
}

/// One SGD step with per-tensor learning rates softplus(rho): p - lr_i * grad_i. With
/// `create_graph` the result stays differentiable in p and rho (training); without, the result is
/// detached and ready for another step (test-time adaptation).
pub fn sgd_step(p: &[Tensor], loss: &Tensor, rho: &Tensor, create_graph: bool) -> Vec<Tensor> {
    let grads = Tensor::run_backward(&[loss], p, create_graph, create_graph);
    let lrs = rho.softplus();
    p.iter()
        .zip(grads)
        .enumerate()
        .map(|(i, (p, g))| {
            let q = p - lrs.get(i as i64) * g;
            if create_graph {
                q
            } else {
                q.detach().set_requires_grad(true)
            }
        })
        .collect()
}

// ---------------------------------------------------------------- meta-training (spec 5.1) --

/// The losses of one task of a meta-step.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct TaskLosses {
    pub value_inner: f64,
    pub value_outer: f64,
    pub policy_inner: f64,
    pub policy_outer: f64,
}

/// One task of a meta-training step: adapts V and pi on `d_in`, evaluates the outer losses with the
/// adapted parameters on `d_out`, and accumulates their gradients (divided by `n_train`, the
/// number of training tasks, as the official code does) into the leaves of `p`. Returns the
/// losses and the adapted parameters (phi', theta'), detached.
pub fn meta_task(
    p: &Params,
    dims: &Dims,
    d_in: &Batch,
    d_out: &Batch,
    n_train: usize,
    cfg: &MacawConfig,
) -> (TaskLosses, Vec<Tensor>, Vec<Tensor>) {
    let l_v_in = value_loss(&p.value, dims, d_in, None, cfg);
    let v2 = sgd_step(&p.value, &l_v_in, &p.rho_v, true);
    let a = cfg.target_vf_alpha;
    let target: Vec<Tensor> =
        tch::no_grad(|| p.value.iter().zip(&v2).map(|(p, q)| p * a + q * (1.0 - a)).collect());
    let l_v_out = value_loss(&v2, dims, d_out, Some(&target), cfg);
    (&l_v_out / n_train as f64).backward();
    let v2: Vec<Tensor> = v2.iter().map(Tensor::detach).collect();
    let l_p_in = policy_loss(&p.policy, dims, &v2, d_in, &p.rho_adv, true, cfg);
    let p2 = sgd_step(&p.policy, &l_p_in, &p.rho_pi, true);
    let l_p_out = policy_loss(&p2, dims, &v2, d_out, &p.rho_adv, false, cfg);
    (&l_p_out / n_train as f64).backward();
    let losses = TaskLosses {
        value_inner: l_v_in.double_value(&[]),
        value_outer: l_v_out.double_value(&[]),
        policy_inner: l_p_in.double_value(&[]),
        policy_outer: l_p_out.double_value(&[]),
    };
    (losses, v2, p2.iter().map(Tensor::detach).collect())
}

/// PyTorch's Adam (`foreach=False`, no weight decay, no amsgrad), over a fixed list of tensors:
/// the same operations in the same order as `torch.optim.adam._single_tensor_adam`.
#[derive(Debug)]
pub struct Adam {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Steps taken per tensor (a tensor without a gradient is skipped, as PyTorch does).
    pub steps: Vec<u64>,
    pub exp_avg: Vec<Tensor>,
    pub exp_avg_sq: Vec<Tensor>,
}

impl Adam {
    pub fn new(params: &[&Tensor], lr: f64) -> Self {
        Self {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            steps: vec![0; params.len()],
            exp_avg: params.iter().map(|p| p.zeros_like()).collect(),
            exp_avg_sq: params.iter().map(|p| p.zeros_like()).collect(),
        }
    }

    pub fn step(&mut self, params: &[&Tensor]) {
        let (b1, b2, lr, eps) = (self.beta1, self.beta2, self.lr, self.eps);
        tch::no_grad(|| {
            for (i, p) in params.iter().enumerate() {
                let grad = p.grad();
                if !grad.defined() {
                    continue;
                }
                self.steps[i] += 1;
                let step = self.steps[i] as f64;
                let _ = self.exp_avg[i].lerp_(&grad, 1.0 - b1);
                // addcmul_(g, g, value=v) computes self + (v * g) * g; tch's has no value argument.
                let _ = self.exp_avg_sq[i].g_mul_scalar_(b2).addcmul_(&(&grad * (1.0 - b2)), &grad);
                let bias_correction1 = 1.0 - b1.powf(step);
                let bias_correction2 = 1.0 - b2.powf(step);
                let step_size = lr / bias_correction1;
                let denom = (self.exp_avg_sq[i].sqrt() / bias_correction2.powf(0.5)) + eps;
                let mut p = p.shallow_clone();
                let _ = p.addcdiv_(&(&self.exp_avg[i] * -step_size), &denom);
            }
        });
    }
}

/// The five outer optimisers of spec 5.1 step 4, in their order.
#[derive(Debug)]
pub struct Optimisers {
    pub adams: [Adam; 5],
}

impl Optimisers {
    pub const GROUPS: [&'static str; 5] = ["value", "policy", "rho_v", "rho_pi", "rho_adv"];

    pub fn new(p: &Params, cfg: &MacawConfig) -> Self {
        let g = p.groups();
        let lrs = [cfg.outer_value_lr, cfg.outer_policy_lr, cfg.lrlr, cfg.lrlr, cfg.lrlr];
        Self { adams: std::array::from_fn(|i| Adam::new(&g[i], lrs[i])) }
    }

    pub fn step(&mut self, p: &Params) {
        for (adam, group) in self.adams.iter_mut().zip(p.groups()) {
            adam.step(&group);
        }
    }
}

/// Statistics of one meta-step.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct StepStats {
    /// Means over the step's tasks.
    pub losses: TaskLosses,
    /// Global norm of the meta-gradient of V, pi (no clipping: the official `grad_clip` is 1e9).
    pub value_grad_norm: f64,
    pub policy_grad_norm: f64,
    /// Mean effective inner learning rates and the advantage coefficient after the step.
    pub value_lr: f64,
    pub policy_lr: f64,
    pub adv_coef: f64,
}

impl StepStats {
    pub fn is_finite(&self) -> bool {
        let l = &self.losses;
        [
            l.value_inner,
            l.value_outer,
            l.policy_inner,
            l.policy_outer,
            self.value_grad_norm,
            self.policy_grad_norm,
        ]
        .iter()
        .all(|v| v.is_finite())
    }
}

fn grad_norm(ts: &[Tensor]) -> f64 {
    ts.iter()
        .map(|t| {
            let g = t.grad();
            if g.defined() {
                // One pass, no temporary (the generator gradients are [in*out+out, 100]).
                g.norm().double_value(&[]).powi(2)
            } else {
                0.0
            }
        })
        .sum::<f64>()
        .sqrt()
}

/// A whole meta-training step over `tasks` (pairs of inner and outer batches): zero the gradients,
/// accumulate every task's meta-gradient, step the five Adams.
pub fn meta_step(
    p: &mut Params,
    opt: &mut Optimisers,
    dims: &Dims,
    tasks: &[(Batch, Batch)],
    n_train: usize,
    cfg: &MacawConfig,
) -> StepStats {
    p.zero_grad();
    let mut sum = TaskLosses::default();
    for (d_in, d_out) in tasks {
        let (l, _, _) = meta_task(p, dims, d_in, d_out, n_train, cfg);
        sum.value_inner += l.value_inner;
        sum.value_outer += l.value_outer;
        sum.policy_inner += l.policy_inner;
        sum.policy_outer += l.policy_outer;
    }
    let n = tasks.len().max(1) as f64;
    let (value_grad_norm, policy_grad_norm) = (grad_norm(&p.value), grad_norm(&p.policy));
    opt.step(p);
    let mean_lr =
        |rho: &Tensor| tch::no_grad(|| rho.softplus().mean(Kind::Double).double_value(&[]));
    StepStats {
        losses: TaskLosses {
            value_inner: sum.value_inner / n,
            value_outer: sum.value_outer / n,
            policy_inner: sum.policy_inner / n,
            policy_outer: sum.policy_outer / n,
        },
        value_grad_norm,
        policy_grad_norm,
        value_lr: mean_lr(&p.rho_v),
        policy_lr: mean_lr(&p.rho_pi),
        adv_coef: tch::no_grad(|| p.rho_adv.softplus().to_kind(Kind::Double).double_value(&[])),
    }
}

// ---------------------------------------------------------------- adaptation (spec 5.4, 5.5) --

/// The result of a test-time adaptation.
#[derive(Debug)]
pub struct Adapted {
    /// phi' and theta'.
    pub value: Vec<Tensor>,
    pub policy: Vec<Tensor>,
    /// Steps taken (equal to `adapt_steps` unless the adaptation diverged).
    pub value_steps: usize,
    pub policy_steps: usize,
}

impl Adapted {
    pub fn diverged(&self, cfg: &MacawConfig) -> bool {
        self.value_steps < cfg.adapt_steps || self.policy_steps < cfg.adapt_steps
    }
}

fn all_finite(ts: &[Tensor]) -> bool {
    ts.iter().all(|t| t.isfinite().all().int64_value(&[]) != 0)
}

/// Test-time adaptation on one batch of a task's data: `cfg.adapt_steps` SGD steps of the inner
/// value loss (MC targets) and of the inner policy loss against the adapted value function, with
/// the learned learning rates, in `cfg.adapt_order`. The meta-parameters are untouched.
///
/// DIFFERENCE: a step whose loss or result is not finite is not taken, and that chain (value or
/// policy) stops there (`Adapted::value_steps` / `policy_steps` say where). The official protocol
/// takes one step; the Prompt-DT protocol's 10 steps can run away before meta-training has shaped
/// the initialisation (measured on Cheetah-Dir from the initial parameters: value loss 1.0e5, then
/// 6.2e10, then NaN), and a NaN action would end the evaluation.
pub fn adapt(p: &Params, dims: &Dims, b: &Batch, cfg: &MacawConfig) -> Adapted {
    let fresh = |ts: &[Tensor]| -> Vec<Tensor> {
        ts.iter().map(|t| t.detach().set_requires_grad(true)).collect()
    };
    let (rho_v, rho_pi, rho_adv) = (p.rho_v.detach(), p.rho_pi.detach(), p.rho_adv.detach());
    let mut out = Adapted {
        value: fresh(&p.value),
        policy: fresh(&p.policy),
        value_steps: 0,
        policy_steps: 0,
    };
    let (mut value_live, mut policy_live) = (true, true);
    let value_step = |out: &mut Adapted, live: &mut bool| {
        if !*live {
            return;
        }
        let loss = value_loss(&out.value, dims, b, None, cfg);
        let next = sgd_step(&out.value, &loss, &rho_v, false);
        if loss.double_value(&[]).is_finite() && all_finite(&next) {
            out.value = next;
            out.value_steps += 1;
        } else {
            *live = false;
        }
    };
    let policy_step = |out: &mut Adapted, live: &mut bool| {
        if !*live {
            return;
        }
        let vd: Vec<Tensor> = out.value.iter().map(Tensor::detach).collect();
        let loss = policy_loss(&out.policy, dims, &vd, b, &rho_adv, true, cfg);
        let next = sgd_step(&out.policy, &loss, &rho_pi, false);
        if loss.double_value(&[]).is_finite() && all_finite(&next) {
            out.policy = next;
            out.policy_steps += 1;
        } else {
            *live = false;
        }
    };
    match cfg.adapt_order {
        AdaptOrder::ValueFirst => {
            for _ in 0..cfg.adapt_steps {
                value_step(&mut out, &mut value_live);
            }
            for _ in 0..cfg.adapt_steps {
                policy_step(&mut out, &mut policy_live);
            }
        }
        AdaptOrder::Interleaved => {
            for _ in 0..cfg.adapt_steps {
                value_step(&mut out, &mut value_live);
                policy_step(&mut out, &mut policy_live);
            }
        }
    }
    out.value = out.value.iter().map(Tensor::detach).collect();
    out.policy = out.policy.iter().map(Tensor::detach).collect();
    out
}

/// The deterministic action clip(mu(s), -1, 1) for a batch of raw observations `[N, O]`.
pub fn act(policy: &[Tensor], dims: &Dims, obs: &Tensor, cfg: &MacawConfig) -> Tensor {
    tch::no_grad(|| {
        policy_forward(policy, dims, obs, None, cfg.hidden_activation).0.clamp(-1.0, 1.0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use pdt_rundir::config::macaw::Preset;

    #[test]
    fn parameter_counts_equal_the_official_networks() {
        // spec 3.3's table (each WLinear: 100 + 101 (in out + out)).
        for (o, a, w, policy, value) in [
            (20, 6, 100, 2_663_263, 2_262_901),
            (20, 6, 300, 20_055_463, 18_907_701),
            (27, 8, 100, 2_760_829, 2_333_601),
            (27, 8, 300, 20_334_829, 19_119_801),
        ] {
            let dims = Dims::new(o, a, w, 3);
            let count = |layers: &[(i64, i64)]| -> i64 {
                layers.iter().map(|&(i, o)| LATENT + (LATENT + 1) * (i * o + o)).sum()
            };
            assert_eq!((count(&dims.policy), count(&dims.value)), (policy, value), "{o}/{a} W {w}");
        }
        let (v, p) = Dims::new(20, 6, 100, 3).names();
        assert_eq!((v.len(), p.len()), (12, 18));
        assert_eq!(v[0], "value.fc_0.z");
        assert_eq!(p[12], "policy.head_0.z");
        assert_eq!(p[17], "policy.head_1.bias");
    }

    #[test]
    fn the_promptdt_preset_differs_from_the_official_in_the_tables_rows_only() {
        let (o, p) =
            (MacawConfig::preset(Preset::Official, 5), MacawConfig::preset(Preset::Promptdt, 5));
        assert_eq!(o, MacawConfig::default());
        assert_eq!((p.width, p.buffer_rows, p.adapt_batch, p.adapt_steps), (300, 20_000, 5, 10));
        let back =
            MacawConfig { width: 100, buffer_rows: 0, adapt_batch: 256, adapt_steps: 1, ..p };
        assert_eq!(back, o);
        assert!(o.validate().is_ok() && p.validate().is_ok());
    }

    #[test]
    fn bad_settings_are_named() {
        for (cfg, name) in [
            (MacawConfig { adapt_batch: 1, ..Default::default() }, "macaw.adapt_batch"),
            (
                MacawConfig { outer_value_lr: f64::NAN, ..Default::default() },
                "macaw.outer_value_lr",
            ),
            (MacawConfig { discount: 1.5, ..Default::default() }, "macaw.discount"),
            (MacawConfig { buffer_skip: 0, ..Default::default() }, "macaw.buffer_skip"),
            (MacawConfig { width: 0, ..Default::default() }, "macaw.width"),
        ] {
            let e = cfg.validate().unwrap_err().to_string();
            assert!(e.contains(name), "{e}");
        }
    }

    #[test]
    fn adaptation_stops_before_a_step_that_is_not_finite() {
        tch::manual_seed(0);
        let cfg = MacawConfig { width: 8, adapt_steps: 10, ..Default::default() };
        let dims = Dims::new(3, 2, 8, 3);
        let p = Params::init(&dims, &cfg, Kind::Float, Device::Cpu);
        // Returns of 1e18: the first value step overshoots far past f32's range.
        let b = Batch {
            obs: Tensor::randn([6, 3], (Kind::Float, Device::Cpu)) * 50.0,
            act: Tensor::zeros([6, 2], (Kind::Float, Device::Cpu)),
            terminal_obs: Tensor::randn([6, 3], (Kind::Float, Device::Cpu)),
            terminal_discount: Tensor::ones([6, 1], (Kind::Float, Device::Cpu)),
            mc_return: Tensor::randn([6, 1], (Kind::Float, Device::Cpu)) * 1e18,
        };
        let a = adapt(&p, &dims, &b, &cfg);
        assert!(a.diverged(&cfg) && a.value_steps < 10, "{} {}", a.value_steps, a.policy_steps);
        assert!(all_finite(&a.value) && all_finite(&a.policy));
        let mu = act(&a.policy, &dims, &b.obs, &cfg);
        assert!(mu.isfinite().all().int64_value(&[]) == 1);
    }
}
