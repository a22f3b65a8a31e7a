//! AdamW and gradient clipping over a pack's stacked parameters (`[N, ...]`): the solo optimiser's
//! ops (`crate::optim`) once per parameter tensor for all runs, with each run's scalars (learning
//! rate, bias corrections, clipping coefficient) as `[N]` tensors broadcast over its row. The
//! number of kernels per step does not grow with N.
//!
//! A (run, parameter) pair updates when the run is stepped and reads the parameter; every other row
//! is kept with `where` (never a product with 0, which would turn a NaN into a NaN), so a run that
//! is not stepped, or a parameter its run never reads, is left bit for bit as it was.

use crate::optim::{AdamWConfig, ParamState};
use std::collections::{BTreeMap, HashMap};
use tch::{Device, Kind, Tensor};

/// Whether a run reads a parameter, so that PyTorch would give it a gradient: never the unused
/// token embedding and prediction heads; the prompt layers only when the run uses a prompt.
pub(super) fn reads(name: &str, uses_prompt: bool) -> bool {
    if name == "transformer.wte.weight"
        || name.starts_with("predict_state.")
        || name.starts_with("predict_return.")
    {
        false
    } else if name.starts_with("prompt_") {
        uses_prompt
    } else {
        true
    }
}

/// One parameter's moments for every run, and each run's step count for it.
#[derive(Debug)]
struct Moments {
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    steps: Vec<u64>,
    /// The run has a state for this parameter (it has had a gradient), as the solo optimiser's
    /// state map has an entry.
    has_state: Vec<bool>,
}

#[derive(Debug)]
pub(super) struct PackedAdamW {
    cfgs: Vec<AdamWConfig>,
    names: Vec<String>,
    /// `[parameter][run]`: see [`reads`].
    used: Vec<Vec<bool>>,
    moments: Vec<Moments>,
    /// `[N]`: each run's clipping threshold.
    max_norm: Tensor,
    device: Device,
}

/// The per-run factors of one update, rows of a `[7, N]` tensor.
const DECAY: i64 = 0; // 1 - lr * weight_decay
const W1: i64 = 1; // 1 - beta1
const B2: i64 = 2; // beta2
const W2: i64 = 3; // 1 - beta2
const BC2_SQRT: i64 = 4; // sqrt(1 - beta2^step)
const EPS: i64 = 5;
const NEG_STEP_SIZE: i64 = 6; // -lr / (1 - beta1^step)

impl PackedAdamW {
    /// Zero moments for `params` (`[N, ...]`, named `names`); `uses_prompt[n]` and `cfgs[n]` per run.
    pub(super) fn new(
        names: &[String],
        params: &[Tensor],
        cfgs: Vec<AdamWConfig>,
        uses_prompt: &[bool],
        device: Device,
    ) -> Self {
        let n = cfgs.len();
        let used =
            names.iter().map(|nm| uses_prompt.iter().map(|&u| reads(nm, u)).collect()).collect();
        let moments = params
            .iter()
            .map(|p| Moments {
                exp_avg: p.zeros_like().detach(),
                exp_avg_sq: p.zeros_like().detach(),
                steps: vec![0; n],
                has_state: vec![false; n],
            })
            .collect();
        let max: Vec<f32> = cfgs.iter().map(|c| c.grad_clip_norm as f32).collect();
        let max_norm = Tensor::from_slice(&max).to_device(device);
        Self { cfgs, names: names.to_vec(), used, moments, max_norm, device }
    }

    fn slots(&self) -> usize {
        self.cfgs.len()
    }

    fn bools(&self, v: &[bool]) -> Tensor {
        Tensor::from_slice(v).to_device(self.device)
    }

    /// The factors of one update for runs at the given step counts (after this step's increment).
    fn factors(&self, steps: &[u64], lrs: &[f64]) -> Tensor {
        let n = self.slots();
        let mut rows = vec![0f32; 7 * n];
        for (s, cfg) in self.cfgs.iter().enumerate() {
            // A run not updated keeps its rows (`where`); step 1 keeps its factors finite.
            let step = steps[s].max(1) as f64;
            let lr = lrs[s];
            let at = |row: i64| row as usize * n + s;
            // As `crate::optim::AdamW::step` computes them, in f64, then used as f32 as libtorch
            // uses a scalar operand of a float tensor.
            rows[at(DECAY)] = (1.0 - lr * cfg.weight_decay) as f32;
            rows[at(W1)] = (1.0 - cfg.beta1) as f32;
            rows[at(B2)] = cfg.beta2 as f32;
            rows[at(W2)] = (1.0 - cfg.beta2) as f32;
            rows[at(BC2_SQRT)] = (1.0 - cfg.beta2.powf(step)).powf(0.5) as f32;
            rows[at(EPS)] = cfg.eps as f32;
            rows[at(NEG_STEP_SIZE)] = (-(lr / (1.0 - cfg.beta1.powf(step)))) as f32;
        }
        Tensor::from_slice(&rows).to_device(self.device).view([7, n as i64])
    }

    /// Clips each run's gradients by its global norm and takes one AdamW step for every (run,
    /// parameter) pair that updates (see the module documentation). `grads[i]` is `None` for a
    /// parameter no run's loss reads. Returns each run's gradient norm before clipping, `[N]`
    /// (0 for a run not stepped).
    pub(super) fn step(
        &mut self,
        params: &[Tensor],
        grads: &[Option<Tensor>],
        active: &[bool],
        lrs: &[f64],
    ) -> Tensor {
        let n = self.slots();
        tch::no_grad(|| {
            let mut masks: HashMap<Vec<bool>, Tensor> = HashMap::new();
            let upd: Vec<Option<Vec<bool>>> = grads
                .iter()
                .enumerate()
                .map(|(i, g)| {
                    g.as_ref().map(|_| (0..n).map(|s| active[s] && self.used[i][s]).collect())
                })
                .collect();
            // Each run's norm of each parameter's gradient, 0 where the pair does not update.
            let mut norms = Vec::with_capacity(grads.len());
            for (g, u) in grads.iter().zip(&upd) {
                let (Some(g), Some(u)) = (g, u) else { continue };
                let mask = masks.entry(u.clone()).or_insert_with(|| self.bools(u));
                let norm =
                    g.reshape([n as i64, -1]).norm_scalaropt_dim(2, [1i64].as_slice(), false);
                norms.push(norm.where_scalarother(mask, 0.0)); // [N]
            }
            if norms.is_empty() {
                return Tensor::zeros([n as i64], (Kind::Float, self.device));
            }
            // clip_grad_norm_ per run: coef = min(max_norm / (total + 1e-6), 1).
            let total = Tensor::stack(&norms, 0).norm_scalaropt_dim(2, [0i64].as_slice(), false); // [N]
            let coef = ((&total + 1e-6).reciprocal() * &self.max_norm).clamp_max(1.0);
            let mut factors: HashMap<Vec<u64>, Tensor> = HashMap::new();
            for (i, (g, u)) in grads.iter().zip(&upd).enumerate() {
                let (Some(g), Some(u)) = (g, u) else { continue };
                if !u.iter().any(|&x| x) {
                    continue;
                }
                let st = &mut self.moments[i];
                for (s, &up) in u.iter().enumerate() {
                    if up {
                        st.steps[s] += 1;
                        st.has_state[s] = true;
                    }
                }
                let steps = st.steps.clone();
                let f = match factors.get(&steps) {
                    Some(f) => f.shallow_clone(),
                    None => {
                        let f = self.factors(&steps, lrs);
                        factors.insert(steps, f.shallow_clone());
                        f
                    }
                };
                let keep = masks.entry(u.clone()).or_insert_with(|| self.bools(u)).shallow_clone();
                let st = &mut self.moments[i];
                // [N, 1, ...]: a run's scalar over its row.
                let mut bshape = vec![n as i64];
                bshape.resize(g.dim(), 1);
                let c = |row: i64| f.get(row).view(bshape.as_slice());
                let mut g = g.shallow_clone(); // a fresh gradient of this step: scaled in place
                let _ = g.g_mul_(&coef.view(bshape.as_slice()));
                let mut p = params[i].shallow_clone();
                if u.iter().all(|&x| x) {
                    // Every row updates: in place, as the solo optimiser (the same elementwise
                    // ops as below, so the same bits).
                    let _ = p.g_mul_(&c(DECAY));
                    let _ = st.exp_avg.lerp_tensor_(&g, &c(W1));
                    let _ = st.exp_avg_sq.g_mul_(&c(B2)).addcmul_(&(&g * c(W2)), &g);
                    let denom = st.exp_avg_sq.sqrt() / c(BC2_SQRT) + c(EPS);
                    let _ = p.addcdiv_(&(&st.exp_avg * c(NEG_STEP_SIZE)), &denom);
                    continue;
                }
                let p_new = &p * c(DECAY);
                let m_new = st.exp_avg.lerp_tensor(&g, &c(W1));
                let v_new = (&st.exp_avg_sq * c(B2)).addcmul(&(&g * c(W2)), &g);
                let denom = v_new.sqrt() / c(BC2_SQRT) + c(EPS);
                let p_new = p_new.addcdiv(&(&m_new * c(NEG_STEP_SIZE)), &denom);
                let keep = keep.view(bshape.as_slice());
                p.copy_(&p_new.where_self(&keep, &p));
                let m = m_new.where_self(&keep, &st.exp_avg);
                st.exp_avg.copy_(&m);
                let v = v_new.where_self(&keep, &st.exp_avg_sq);
                st.exp_avg_sq.copy_(&v);
            }
            total
        })
    }

    /// Run `slot`'s moments as the solo optimiser holds them (only parameters with a state).
    pub(super) fn export(&self, slot: usize) -> BTreeMap<String, ParamState> {
        tch::no_grad(|| {
            self.names
                .iter()
                .zip(&self.moments)
                .filter(|(_, m)| m.has_state[slot])
                .map(|(name, m)| {
                    let st = ParamState {
                        step: m.steps[slot],
                        exp_avg: m.exp_avg.select(0, slot as i64).copy(),
                        exp_avg_sq: m.exp_avg_sq.select(0, slot as i64).copy(),
                    };
                    (name.clone(), st)
                })
                .collect()
        })
    }

    /// Sets run `slot`'s moments (parameters absent from `moments` get none: zero, step 0).
    pub(super) fn import(
        &mut self,
        slot: usize,
        moments: &BTreeMap<String, ParamState>,
    ) -> Result<(), String> {
        for (name, st) in moments {
            let i = self
                .names
                .iter()
                .position(|n| n == name)
                .ok_or_else(|| format!("moments of `{name}`, not a parameter of the model"))?;
            let want = &self.moments[i].exp_avg.size()[1..];
            for t in [&st.exp_avg, &st.exp_avg_sq] {
                if t.size() != want || t.kind() != Kind::Float {
                    return Err(format!(
                        "moments of `{name}` have shape {:?} {:?}, expected {want:?} Float",
                        t.size(),
                        t.kind()
                    ));
                }
            }
        }
        tch::no_grad(|| {
            for (name, m) in self.names.iter().zip(&mut self.moments) {
                let row = slot as i64;
                match moments.get(name) {
                    Some(st) => {
                        m.exp_avg.select(0, row).copy_(&st.exp_avg);
                        m.exp_avg_sq.select(0, row).copy_(&st.exp_avg_sq);
                        m.steps[slot] = st.step;
                        m.has_state[slot] = true;
                    }
                    None => {
                        let _ = m.exp_avg.select(0, row).zero_();
                        let _ = m.exp_avg_sq.select(0, row).zero_();
                        m.steps[slot] = 0;
                        m.has_state[slot] = false;
                    }
                }
            }
        });
        Ok(())
    }
}
