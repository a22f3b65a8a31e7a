//! AdamW and global gradient clipping over one contiguous buffer per run: the same maths as
//! [`AdamW`](super::adamw::AdamW), in a fixed number of kernel launches per step whatever the number
//! of parameter tensors (on CUDA the per-tensor loops are launch-bound; tch 0.24 binds no
//! `_foreach_*` or `_fused_adamw_`).
//!
//! At construction every optimised parameter is copied into one flat buffer and its `VarStore`
//! variable is re-pointed (`set_data`) at a view of that buffer, so that the model trains through
//! the views, `checkpoint::load`'s in-place copies land in the buffer and whole-buffer updates are
//! what the model sees. The Adam moments are flat buffers with the same layout.
//!
//! On CUDA a step launches, independent of the number of tensors: 1 `_chunk_cat` (gathering the
//! gradients), 6 for clipping (`norm`, `+ 1e-6`, `reciprocal`, `* max_norm`, `clamp_max`, `mul_`),
//! and 10 for the update (`mul_`, `lerp_`, `mul_`, `mul`, `addcmul_`, `sqrt`, `div`, `add`, `mul`,
//! `addcdiv_`): 17 kernels, plus the one read of the total norm for the caller. On CPU the update's
//! 10 ops run per piece of [`CPU_CHUNK`] elements (cache-sized; 14 pieces for the reference
//! model's 0.86 M parameters), which changes no result: every op is element-wise.
//!
//! Parameters without a gradient (PyTorch's `grad is None`: `wte`, the unused heads, the prompt
//! layers of a no-prompt variant) get no update, no weight decay and no step count, as in
//! PyTorch. They are simply not gathered: the first time the set of parameters with a gradient is
//! not a prefix of the buffer, the buffers are laid out again with those parameters first (in
//! optimisation order), so the update covers one contiguous prefix and the other slices are never
//! written. Parameters whose step counts differ (a state loaded from elsewhere) are updated one
//! slice at a time with their own counts: correct, just not fast.
//!
//! Not bit for bit with PyTorch: the total norm is one reduction over the whole buffer instead of
//! the norm of the per-tensor norms, so the clipping coefficient differs in the last bits (the
//! element-wise update itself is the same ops). See docs/reproducibility.md for the measured
//! tolerance.

use super::adamw::{adamw_update, optimised_params, Grads, Moments, ParamState};
use pdt_rundir::config::AdamWConfig;
use std::collections::BTreeMap;
use std::sync::Arc;
use tch::{nn::VarStore, Tensor};

/// A state that does not fit this optimiser's parameters.
#[derive(Debug, thiserror::Error)]
pub enum OptimError {
    #[error("optimiser state for `{0}`, which is not an optimised parameter")]
    UnknownParameter(String),
    #[error("optimiser state `{name}` has shape {got:?}, the parameter has {expected:?}")]
    Shape { name: String, got: Vec<i64>, expected: Vec<i64> },
}

/// Where one tensor lies in a flat buffer (elements).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Slot {
    offset: i64,
    numel: i64,
}

/// The gradients of one step gathered into one buffer, the present parameters in the
/// optimiser's layout order.
#[derive(Debug)]
pub struct FlatGrads {
    /// `[n]`: every present gradient flattened, back to back.
    buf: Tensor,
    /// Per optimised parameter (optimisation order): its slice of `buf`, `None` without gradient.
    slots: Vec<Option<Slot>>,
    /// The parameters' shapes (optimisation order), to hand the gradients out per tensor.
    shapes: Arc<[Vec<i64>]>,
    /// The optimiser's layout generation `buf` was gathered for (its prefix, in that layout).
    layout: u64,
}

impl FlatGrads {
    /// The gradient buffer, `[n]` (the present parameters' gradients back to back).
    pub fn buffer(&self) -> &Tensor {
        &self.buf
    }

    /// The gradients per parameter, as views of the buffer (in-place changes reach it).
    pub fn per_param(&self) -> Grads {
        Grads(
            self.slots
                .iter()
                .zip(self.shapes.iter())
                .map(|(s, shape)| {
                    s.map(|s| self.buf.narrow(0, s.offset, s.numel).view(shape.as_slice()))
                })
                .collect(),
        )
    }
}

/// AdamW over one flat buffer holding every optimised variable of a `VarStore`.
#[derive(Debug)]
pub struct FlatAdamW {
    pub cfg: AdamWConfig,
    names: Vec<String>,
    /// Shallow copies of the `VarStore` variables: `set_data` on them re-points the variables.
    params: Vec<Tensor>,
    shapes: Arc<[Vec<i64>]>,
    /// Per parameter (optimisation order): its slice of `weights`, `exp_avg` and `exp_avg_sq`.
    slots: Vec<Slot>,
    weights: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    /// Per parameter: AdamW steps taken (0: no state yet, as PyTorch before a first gradient).
    steps: Vec<u64>,
    /// Bumped at every new layout, so that gradients gathered for an older one are not applied as
    /// one prefix.
    layout: u64,
    /// Elements per piece of the update: the whole prefix at once on CUDA (launches are what
    /// costs there); on CPU [`CPU_CHUNK`], so that each piece's ten ops run on data in cache.
    chunk: Option<i64>,
}

/// Elements per piece of the CPU update: 256 KiB per buffer, so the weights, both moments, the
/// gradient and the temporaries of one piece stay in a core's L2 cache. Whole-buffer ops (0.86 M
/// elements) stream every buffer through memory ten times and took 2x the per-tensor loop's time
/// (1 thread, AMD EPYC); pieces of 64-128 Ki elements took 0.7x.
pub const CPU_CHUNK: i64 = 65_536;

impl FlatAdamW {
    /// Optimises the same variables as [`AdamW::new`](crate::optim::AdamW::new) with the same
    /// `order`, copying them into one buffer and re-pointing each variable at its slice.
    pub fn new(vs: &VarStore, order: &[String], cfg: AdamWConfig) -> Self {
        let (names, params): (Vec<String>, Vec<Tensor>) =
            optimised_params(vs, order).into_iter().unzip();
        let shapes: Arc<[Vec<i64>]> = params.iter().map(|p| p.size()).collect();
        let n = params.len();
        let empty = Tensor::zeros([0], (tch::Kind::Float, vs.device()));
        let mut me = Self {
            cfg,
            names,
            params,
            shapes,
            slots: vec![Slot { offset: 0, numel: 0 }; n],
            weights: empty.shallow_clone(),
            exp_avg: empty.shallow_clone(),
            exp_avg_sq: empty,
            steps: vec![0; n],
            layout: 0,
            chunk: (!vs.device().is_cuda()).then_some(CPU_CHUNK),
        };
        me.lay_out(&(0..n).collect::<Vec<_>>(), false);
        me
    }

    /// Elements per piece of the update (`None`: the whole buffer at once); the default is
    /// [`CPU_CHUNK`] on CPU and `None` on CUDA. Results do not depend on it.
    pub fn set_chunk(&mut self, elements: Option<i64>) {
        self.chunk = elements;
    }

    /// Names of the optimised parameters, in optimisation order.
    pub fn param_names(&self) -> impl Iterator<Item = &str> {
        self.names.iter().map(|n| n.as_str())
    }

    /// The flat weight buffer, `[total]` (every optimised parameter's values, in layout order).
    pub fn weights(&self) -> &Tensor {
        &self.weights
    }

    /// Builds new buffers with the parameters in `order` (indices in optimisation order),
    /// reading each parameter's values through the parameter itself (so a parameter that
    /// something else re-pointed is adopted with its current values) and its moments from the old
    /// buffers (`moments = false` at construction: zeros), then re-points the parameters.
    fn lay_out(&mut self, order: &[usize], moments: bool) {
        tch::no_grad(|| {
            let gather = |parts: Vec<Tensor>, like: &Tensor| {
                if parts.is_empty() {
                    like.zeros_like()
                } else {
                    Tensor::cat(&parts, 0)
                }
            };
            let flat_of = |t: &Tensor| t.detach().reshape([-1]);
            let weights =
                gather(order.iter().map(|&i| flat_of(&self.params[i])).collect(), &self.weights);
            let (exp_avg, exp_avg_sq) = if moments {
                let slices = |buf: &Tensor| -> Vec<Tensor> {
                    order
                        .iter()
                        .map(|&i| buf.narrow(0, self.slots[i].offset, self.slots[i].numel))
                        .collect()
                };
                (
                    gather(slices(&self.exp_avg), &weights),
                    gather(slices(&self.exp_avg_sq), &weights),
                )
            } else {
                (weights.zeros_like(), weights.zeros_like())
            };
            let mut offset = 0;
            for &i in order {
                let numel = self.shapes[i].iter().product::<i64>();
                self.slots[i] = Slot { offset, numel };
                let view = weights.narrow(0, offset, numel).view(self.shapes[i].as_slice());
                self.params[i].set_data(&view);
                offset += numel;
            }
            self.weights = weights;
            self.exp_avg = exp_avg;
            self.exp_avg_sq = exp_avg_sq;
        });
        self.layout += 1;
    }

    /// The parameters' indices in the order their slices lie in the buffers.
    fn layout_order(&self) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.params.len()).collect();
        order.sort_by_key(|&i| self.slots[i].offset);
        order
    }

    /// Whether every parameter still lies where this optimiser put it. Another optimiser built
    /// on the same `VarStore` later (MT-BC-Finetune's per-task one) re-points the variables at its
    /// own buffer; this optimiser then adopts them back, with their current values.
    fn backed(&self) -> bool {
        let base = self.weights.data_ptr() as usize;
        let elt = self.weights.kind().elt_size_in_bytes();
        self.params
            .iter()
            .zip(&self.slots)
            .all(|(p, s)| p.data_ptr() as usize == base + s.offset as usize * elt)
    }

    fn adopt_if_moved(&mut self) {
        if !self.backed() {
            self.lay_out(&self.layout_order(), true);
        }
    }

    /// Gradients of `loss` with respect to every optimised parameter, gathered into one buffer.
    /// As [`AdamW::backward`](crate::optim::AdamW::backward), parameters that do not influence
    /// the loss have none.
    pub fn backward(&mut self, loss: &Tensor) -> FlatGrads {
        let grads = {
            let inputs: Vec<&Tensor> = self.params.iter().collect();
            Tensor::run_backward(&[loss], &inputs, false, false)
        };
        let grads = Grads(grads.into_iter().map(|g| g.defined().then_some(g)).collect());
        self.gather(&grads)
    }

    /// Gathers per-parameter gradients (optimisation order) into one buffer: one `_chunk_cat`.
    /// Lays the buffers out again first if the parameters with a gradient are not a prefix of them.
    pub fn gather(&mut self, grads: &Grads) -> FlatGrads {
        self.adopt_if_moved();
        let present = |i: usize| grads.0.get(i).is_some_and(|g| g.is_some());
        let order = self.layout_order();
        let n_present = (0..self.params.len()).filter(|&i| present(i)).count();
        if !order[..n_present].iter().all(|&i| present(i)) {
            let (mut first, rest): (Vec<usize>, Vec<usize>) =
                (0..self.params.len()).partition(|&i| present(i));
            first.extend(rest);
            self.lay_out(&first, true);
        }
        let mut slots = vec![None; self.params.len()];
        let mut parts = Vec::with_capacity(n_present);
        let mut offset = 0;
        for i in self.layout_order().into_iter().take(n_present) {
            if let Some(Some(g)) = grads.0.get(i) {
                let numel = self.slots[i].numel;
                slots[i] = Some(Slot { offset, numel });
                // (No operator for a gradient that is contiguous already.)
                parts.push(g.contiguous());
                offset += numel;
            }
        }
        let buf = if parts.is_empty() {
            self.weights.narrow(0, 0, 0).zeros_like()
        } else {
            // Each part flattened and concatenated: on CUDA one operator and one kernel for
            // contiguous parts (`_chunk_cat`, libtorch's gradient gather for FSDP2), where a reshape
            // per part and a `cat` dispatch about two operators per parameter tensor; on the CPU
            // libtorch runs those reshapes and `cat` for it. `[1, total]` -> `[total]`.
            // (Should libtorch refuse it, the reshapes and `cat` it stands for.)
            match Tensor::f_internal_chunk_cat(&parts, 0, 1) {
                Ok(g) => g.view([-1]),
                Err(_) => {
                    Tensor::cat(&parts.iter().map(|p| p.reshape([-1])).collect::<Vec<_>>(), 0)
                }
            }
        };
        FlatGrads { buf, slots, shapes: self.shapes.clone(), layout: self.layout }
    }

    /// `clip_grad_norm_` over the whole gradient buffer: one norm, one scale. Returns the total
    /// norm before clipping, not read (a 0-d zero on the CPU when no parameter has a gradient, as
    /// `AdamW::clip_grad_norm`).
    pub fn clip_grad_norm(&self, grads: &mut FlatGrads, max_norm: f64) -> Tensor {
        if grads.slots.iter().all(Option::is_none) {
            return Tensor::from(0f32);
        }
        let total = grads.buf.norm();
        // As `AdamW::clip_grad_norm`: Python's `max_norm / (total + 1e-6)`, clamped at 1.
        let coef = ((&total + 1e-6).reciprocal() * max_norm).clamp_max(1.0);
        let _ = grads.buf.g_mul_(&coef);
        total
    }

    /// One AdamW update at learning rate `lr` of every parameter that has a gradient.
    pub fn step(&mut self, grads: &FlatGrads, lr: f64) {
        self.adopt_if_moved();
        let present: Vec<usize> = (0..self.params.len())
            .filter(|&i| grads.slots.get(i).is_some_and(|s| s.is_some()))
            .collect();
        let Some(&first) = present.first() else { return };
        let step = self.steps[first] + 1;
        let one_prefix =
            grads.layout == self.layout && present.iter().all(|&i| self.steps[i] + 1 == step);
        tch::no_grad(|| {
            if one_prefix {
                // The present parameters are the buffers' first `n` elements, in `buf`'s order.
                let n = grads.buf.size()[0];
                let chunk = self.chunk.unwrap_or(n).max(1);
                let mut start = 0;
                while start < n {
                    let len = chunk.min(n - start);
                    let mut w = self.weights.narrow(0, start, len);
                    let moments = Moments {
                        exp_avg: &mut self.exp_avg.narrow(0, start, len),
                        exp_avg_sq: &mut self.exp_avg_sq.narrow(0, start, len),
                    };
                    adamw_update(
                        &mut w,
                        moments,
                        &grads.buf.narrow(0, start, len),
                        step,
                        lr,
                        &self.cfg,
                    );
                    start += len;
                }
            } else {
                for &i in &present {
                    let (s, Some(g)) = (self.slots[i], grads.slots[i]) else { continue };
                    let mut w = self.weights.narrow(0, s.offset, s.numel);
                    let moments = Moments {
                        exp_avg: &mut self.exp_avg.narrow(0, s.offset, s.numel),
                        exp_avg_sq: &mut self.exp_avg_sq.narrow(0, s.offset, s.numel),
                    };
                    let grad = grads.buf.narrow(0, g.offset, g.numel);
                    adamw_update(&mut w, moments, &grad, self.steps[i] + 1, lr, &self.cfg);
                }
            }
        });
        for &i in &present {
            self.steps[i] += 1;
        }
    }

    /// The state per parameter name, as `AdamW::state` holds it (copies, shaped like the
    /// parameters), for the parameters that have one (step > 0).
    pub fn state(&self) -> BTreeMap<String, ParamState> {
        let piece = |buf: &Tensor, i: usize| {
            let s = self.slots[i];
            buf.narrow(0, s.offset, s.numel).view(self.shapes[i].as_slice()).copy()
        };
        (0..self.params.len())
            .filter(|&i| self.steps[i] > 0)
            .map(|i| {
                let st = ParamState {
                    step: self.steps[i],
                    exp_avg: piece(&self.exp_avg, i),
                    exp_avg_sq: piece(&self.exp_avg_sq, i),
                };
                (self.names[i].clone(), st)
            })
            .collect()
    }

    /// Replaces the whole state by `state` (per parameter name, as [`FlatAdamW::state`] or
    /// `AdamW::state` hold it): parameters missing from it start afresh (step 0, zero moments).
    /// Nothing changes when an entry names no optimised parameter or has another shape.
    pub fn set_state(&mut self, state: &BTreeMap<String, ParamState>) -> Result<(), OptimError> {
        let index: BTreeMap<&str, usize> =
            self.names.iter().enumerate().map(|(i, n)| (n.as_str(), i)).collect();
        let mut placed = Vec::with_capacity(state.len());
        for (name, st) in state {
            let &i = index
                .get(name.as_str())
                .ok_or_else(|| OptimError::UnknownParameter(name.clone()))?;
            for t in [&st.exp_avg, &st.exp_avg_sq] {
                if t.size() != self.shapes[i] {
                    return Err(OptimError::Shape {
                        name: name.clone(),
                        got: t.size(),
                        expected: self.shapes[i].clone(),
                    });
                }
            }
            placed.push((i, st));
        }
        self.adopt_if_moved();
        tch::no_grad(|| {
            let _ = self.exp_avg.zero_();
            let _ = self.exp_avg_sq.zero_();
            self.steps.iter_mut().for_each(|s| *s = 0);
            for (i, st) in placed {
                let s = self.slots[i];
                self.exp_avg.narrow(0, s.offset, s.numel).copy_(&st.exp_avg.reshape([-1]));
                self.exp_avg_sq.narrow(0, s.offset, s.numel).copy_(&st.exp_avg_sq.reshape([-1]));
                self.steps[i] = st.step;
            }
        });
        Ok(())
    }
}
