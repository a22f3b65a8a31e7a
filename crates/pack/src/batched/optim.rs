//! AdamW and gradient clipping over a pack's stacked parameters (`[N, ...]`): the solo optimiser's
//! ops (`pdt_train::optim`) once per parameter tensor for all runs, with each run's scalars (learning
//! rate, bias corrections, clipping coefficient) as `[N]` tensors broadcast over its row. The
//! number of kernels per step does not grow with N.
//!
//! A (run, parameter) pair updates when the run is stepped and reads the parameter; every other row
//! is kept with `where` (never a product with 0, which would turn a NaN into a NaN), so a run that
//! is not stepped, or a parameter its run never reads, is left bit for bit as it was.
//!
//! Flat mode (`optim.flat`, on CUDA by default, as the solo optimiser): the pack's weights and
//! moments live in run-major buffers `[N, total]`, each parameter a view of its columns (the model's
//! weight tensors are re-pointed there with `set_data`, so they are strided in the run dimension).
//! A step then gathers every gradient into one `[N, prefix]` buffer (one `_chunk_cat`) and clips and
//! updates all runs and parameters at once: about 20 kernels per step whatever N and the number of
//! parameter tensors, where the per-tensor loop launches about 15 per tensor (some 900 for the
//! reference model). The parameters some run reads come first, so the columns updated are one
//! prefix. The element-wise update is the same ops as the per-tensor loop; the clipping norm is one
//! reduction per run instead of the norm of the per-tensor norms, so it differs in the last bits
//! (as the solo flat optimiser's, `pdt_train::optim::flat`). A step whose runs' step counts differ
//! between parameters (a state imported from elsewhere) takes the per-tensor loop over the views.

use pdt_rundir::config::AdamWConfig;
use pdt_torch::device::upload;
use pdt_train::optim::ParamState;
use std::collections::{BTreeMap, HashMap};
use tch::{Device, Kind, Tensor};

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
    /// Per parameter (in flat mode, views of the flat moment buffers).
    moments: Vec<Moments>,
    /// `[N]`: each run's clipping threshold.
    max_norm: Tensor,
    device: Device,
    flat: Option<Flat>,
}

/// The run-major buffers of flat mode (see the module documentation).
#[derive(Debug)]
struct Flat {
    /// `[N, total]`: every run's weights, the model's weight tensors are views of its columns.
    weights: Tensor,
    /// `[N, total]` each, the moments' views likewise.
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    /// The parameters some run reads, in column order (their columns are `[0, prefix)`).
    read: Vec<usize>,
    /// Per parameter: its number of elements per run.
    numel: Vec<i64>,
    prefix: i64,
    /// Per step's pattern of stepped runs: which (run, column) pairs update, `[N, prefix]`; `None`
    /// when every pair does.
    keep: HashMap<Vec<bool>, Option<Tensor>>,
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
    /// Zero moments for `params` (`[N, ...]`, named `names`); `cfgs[n]` per run, `used[p][n]`
    /// whether run `n` reads parameter `p` (gets a gradient for it).
    /// `flat`: flat mode, which re-points `params` (the model's weights) at views of one buffer,
    /// their values kept.
    pub(super) fn new(
        names: &[String],
        params: &[Tensor],
        cfgs: Vec<AdamWConfig>,
        used: Vec<Vec<bool>>,
        device: Device,
        flat: bool,
    ) -> Self {
        let n = cfgs.len();
        let (moments, flat) = if flat {
            let (m, f) = Flat::new(params, &used, n);
            (m, Some(f))
        } else {
            let m = params
                .iter()
                .map(|p| Moments {
                    exp_avg: p.zeros_like().detach(),
                    exp_avg_sq: p.zeros_like().detach(),
                    steps: vec![0; n],
                    has_state: vec![false; n],
                })
                .collect();
            (m, None)
        };
        let max: Vec<f32> = cfgs.iter().map(|c| c.grad_clip_norm as f32).collect();
        let max_norm = upload(&max, device);
        Self { cfgs, names: names.to_vec(), used, moments, max_norm, device, flat }
    }

    /// Whether the weights and moments live in flat buffers.
    pub(super) fn is_flat(&self) -> bool {
        self.flat.is_some()
    }

    fn slots(&self) -> usize {
        self.cfgs.len()
    }

    fn bools(&self, v: &[bool]) -> Tensor {
        upload(v, self.device)
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
            // As `pdt_train::optim::AdamW::step` computes them, in f64, then used as f32 as libtorch
            // uses a scalar operand of a float tensor.
            rows[at(DECAY)] = (1.0 - lr * cfg.weight_decay) as f32;
            rows[at(W1)] = (1.0 - cfg.beta1) as f32;
            rows[at(B2)] = cfg.beta2 as f32;
            rows[at(W2)] = (1.0 - cfg.beta2) as f32;
            rows[at(BC2_SQRT)] = (1.0 - cfg.beta2.powf(step)).powf(0.5) as f32;
            rows[at(EPS)] = cfg.eps as f32;
            rows[at(NEG_STEP_SIZE)] = (-(lr / (1.0 - cfg.beta1.powf(step)))) as f32;
        }
        upload(&rows, self.device).view([7, n as i64])
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
        if let Some(total) = self.flat_step(grads, active, lrs) {
            return total;
        }
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
                // A fresh gradient of this step: scaled in place. At the weight's shape (a bound
                // broadcast view's gradient, `PackedPromptDt::bind_broadcast`, has a unit
                // dimension more).
                let mut g = if g.dim() == params[i].dim() {
                    g.shallow_clone()
                } else {
                    g.view(params[i].size().as_slice())
                };
                // [N, 1, ...]: a run's scalar over its row.
                let mut bshape = vec![n as i64];
                bshape.resize(g.dim(), 1);
                let c = |row: i64| f.get(row).view(bshape.as_slice());
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

impl Flat {
    /// Copies `params` (`[N, ...]` each) into run-major buffers, the parameters some run reads
    /// first, re-points each parameter at its columns, and gives zero moments as views likewise.
    fn new(params: &[Tensor], used: &[Vec<bool>], n: usize) -> (Vec<Moments>, Self) {
        let n = n as i64;
        let numel: Vec<i64> = params.iter().map(|p| p.numel() as i64 / n.max(1)).collect();
        let read: Vec<usize> = (0..params.len()).filter(|&i| used[i].iter().any(|&u| u)).collect();
        let unread = (0..params.len()).filter(|&i| !used[i].iter().any(|&u| u));
        let order: Vec<usize> = read.iter().copied().chain(unread).collect();
        let prefix: i64 = read.iter().map(|&i| numel[i]).sum();
        tch::no_grad(|| {
            let parts: Vec<Tensor> = order.iter().map(|&i| params[i].reshape([n, -1])).collect();
            let weights = Tensor::cat(&parts, 1); // [N, total]
            let exp_avg = weights.zeros_like();
            let exp_avg_sq = weights.zeros_like();
            let mut moments: Vec<Option<Moments>> = (0..params.len()).map(|_| None).collect();
            let mut offset = 0;
            for &i in &order {
                let shape = params[i].size(); // [N, solo shape]
                let view = |b: &Tensor| b.narrow(1, offset, numel[i]).view(shape.as_slice());
                // The model's weight tensor itself (a shallow copy shares it): from now on its
                // values are the buffer's columns, strided by `total` in the run dimension.
                params[i].shallow_clone().set_data(&view(&weights));
                moments[i] = Some(Moments {
                    exp_avg: view(&exp_avg),
                    exp_avg_sq: view(&exp_avg_sq),
                    steps: vec![0; n as usize],
                    has_state: vec![false; n as usize],
                });
                offset += numel[i];
            }
            let moments = moments.into_iter().flatten().collect();
            let keep = HashMap::new();
            (moments, Self { weights, exp_avg, exp_avg_sq, read, numel, prefix, keep })
        })
    }

    /// Which (run, column) pairs of the prefix update when the runs `active` are stepped; `None`
    /// when every pair does. Cached per pattern (a pack's patterns are few: all runs, then the
    /// runs still going near the end).
    fn keep(&mut self, used: &[Vec<bool>], active: &[bool], device: Device) -> Option<Tensor> {
        let (read, numel) = (&self.read, &self.numel);
        self.keep
            .entry(active.to_vec())
            .or_insert_with(|| {
                let pair = |s: usize, i: usize| active[s] && used[i][s];
                if (0..active.len()).all(|s| read.iter().all(|&i| pair(s, i))) {
                    return None;
                }
                let mut m = Vec::with_capacity(active.len() * self.prefix as usize);
                for s in 0..active.len() {
                    for &i in read {
                        m.extend(std::iter::repeat_n(pair(s, i), numel[i] as usize));
                    }
                }
                let m = upload(&m, device);
                Some(m.view([active.len() as i64, self.prefix]))
            })
            .as_ref()
            .map(Tensor::shallow_clone)
    }
}

impl PackedAdamW {
    /// The flat step (module documentation): `None`, with nothing changed, where it does not
    /// apply (not in flat mode; a run whose parameters are at different step counts; a parameter
    /// that would update without a gradient), so that the per-tensor loop takes the step.
    fn flat_step(
        &mut self,
        grads: &[Option<Tensor>],
        active: &[bool],
        lrs: &[f64],
    ) -> Option<Tensor> {
        let n = self.slots();
        let fl = self.flat.as_ref()?;
        // Each stepped run's one step count over the parameters it updates.
        let mut count: Vec<Option<u64>> = vec![None; n];
        for &i in &fl.read {
            for s in (0..n).filter(|&s| active[s] && self.used[i][s]) {
                grads[i].as_ref()?;
                let c = self.moments[i].steps[s];
                match count[s] {
                    None => count[s] = Some(c),
                    Some(k) if k != c => return None,
                    Some(_) => {}
                }
            }
        }
        let device = self.device;
        let (nn, prefix) = (n as i64, fl.prefix);
        let parts: Vec<Tensor> = fl
            .read
            .iter()
            .map(|&i| match &grads[i] {
                // (`contiguous` is no operator for a gradient that already is: all but those of
                // the weights `nn.Linear` reads transposed.)
                Some(g) => g.contiguous(),
                // Read by a run not stepped now: no pair of it updates (`keep`).
                None => Tensor::zeros([nn, fl.numel[i]], (Kind::Float, device)),
            })
            .collect();
        let used = &self.used;
        let keep = self.flat.as_mut()?.keep(used, active, device);
        let fl = self.flat.as_ref()?;
        let steps: Vec<u64> = count.iter().map(|c| c.map_or(0, |c| c + 1)).collect();
        let f = self.factors(&steps, lrs);
        let total = tch::no_grad(|| {
            // Each part `[N, ...]` flattened per run and concatenated: `[N, prefix]`. On CUDA one
            // operator and one kernel for contiguous parts (`_chunk_cat`, as FSDP2 gathers its
            // gradients), where a reshape per part and a `cat` dispatch about two operators per
            // parameter tensor; on the CPU libtorch runs those same reshapes and `cat` for it.
            // (Should libtorch refuse it, the reshapes and `cat` it stands for.)
            let mut g = Tensor::f_internal_chunk_cat(&parts, 0, nn).unwrap_or_else(|_| {
                let flat: Vec<Tensor> = parts.iter().map(|p| p.reshape([nn, -1])).collect();
                Tensor::cat(&flat, 1)
            }); // [N, prefix]
            if let Some(k) = &keep {
                g = g.where_scalarother(k, 0.0);
            }
            // clip_grad_norm_ per run over its updating pairs: coef = min(max / (total + 1e-6), 1).
            let total = g.norm_scalaropt_dim(2, [1i64].as_slice(), false); // [N]
            let coef = ((&total + 1e-6).reciprocal() * &self.max_norm).clamp_max(1.0);
            let _ = g.g_mul_(&coef.view([nn, 1]));
            let c = |row: i64| f.get(row).view([nn, 1]);
            let mut p = fl.weights.narrow(1, 0, prefix);
            let mut m = fl.exp_avg.narrow(1, 0, prefix);
            let mut v = fl.exp_avg_sq.narrow(1, 0, prefix);
            match &keep {
                None => {
                    // The per-tensor loop's in-place ops, over every run and parameter at once.
                    let _ = p.g_mul_(&c(DECAY));
                    let _ = m.lerp_tensor_(&g, &c(W1));
                    let _ = v.g_mul_(&c(B2)).addcmul_(&(&g * c(W2)), &g);
                    let denom = v.sqrt() / c(BC2_SQRT) + c(EPS);
                    let _ = p.addcdiv_(&(&m * c(NEG_STEP_SIZE)), &denom);
                }
                Some(k) => {
                    let m_new = m.lerp_tensor(&g, &c(W1));
                    let v_new = (&v * c(B2)).addcmul(&(&g * c(W2)), &g);
                    let denom = v_new.sqrt() / c(BC2_SQRT) + c(EPS);
                    let p_new = (&p * c(DECAY)).addcdiv(&(&m_new * c(NEG_STEP_SIZE)), &denom);
                    p.copy_(&p_new.where_self(k, &p));
                    m.copy_(&m_new.where_self(k, &m));
                    v.copy_(&v_new.where_self(k, &v));
                }
            }
            // A run not stepped has every pair kept, so its row of `g`, and its norm, is 0.
            total
        });
        for &i in &fl.read {
            for s in (0..n).filter(|&s| active[s] && self.used[i][s]) {
                self.moments[i].steps[s] += 1;
                self.moments[i].has_state[s] = true;
            }
        }
        Some(total)
    }
}
