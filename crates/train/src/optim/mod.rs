//! The optimisers of a training step. [`adamw`]: AdamW, warm-up schedule and gradient clipping,
//! op for op as PyTorch 2.11 does them on CPU (bit for bit). [`flat`]: the same maths over one flat
//! buffer per run, in a fixed handful of kernels (CUDA's default). [`Optimizer`]: either, as
//! `optim.flat` chooses, behind one API.

pub mod adamw;
pub mod flat;

pub use adamw::{AdamW, Grads, ParamState};
pub use flat::{FlatAdamW, FlatGrads, OptimError, CPU_CHUNK};

use pdt_rundir::config::AdamWConfig;
use std::collections::BTreeMap;
use tch::{nn::VarStore, Tensor};

/// Either optimiser, as `optim.flat` chooses, behind one API (the learners and the training step
/// hold this).
#[derive(Debug)]
pub enum Optimizer {
    /// PyTorch's single-tensor loops: bit for bit on CPU.
    PerTensor(AdamW),
    /// One flat buffer: a fixed handful of kernels per step.
    Flat(FlatAdamW),
}

/// The gradients of one step, as the optimiser that computed them holds them.
#[derive(Debug)]
pub enum Gradients {
    PerTensor(Grads),
    Flat(FlatGrads),
}

impl Optimizer {
    /// The optimiser `cfg.flat` asks for on the device of `vs` (`auto`: flat on CUDA only), over
    /// the variables [`AdamW::new`] would optimise.
    pub fn new(vs: &VarStore, order: &[String], cfg: AdamWConfig) -> Self {
        if cfg.flat.use_flat(vs.device().is_cuda()) {
            Self::Flat(FlatAdamW::new(vs, order, cfg))
        } else {
            Self::PerTensor(AdamW::new(vs, order, cfg))
        }
    }

    pub fn cfg(&self) -> &AdamWConfig {
        match self {
            Self::PerTensor(o) => &o.cfg,
            Self::Flat(o) => &o.cfg,
        }
    }

    pub fn is_flat(&self) -> bool {
        matches!(self, Self::Flat(_))
    }

    /// Names of the optimised parameters, in optimisation order.
    pub fn param_names(&self) -> Vec<&str> {
        match self {
            Self::PerTensor(o) => o.param_names().collect(),
            Self::Flat(o) => o.param_names().collect(),
        }
    }

    /// See [`AdamW::backward`].
    pub fn backward(&mut self, loss: &Tensor) -> Gradients {
        match self {
            Self::PerTensor(o) => Gradients::PerTensor(o.backward(loss)),
            Self::Flat(o) => Gradients::Flat(o.backward(loss)),
        }
    }

    /// See [`AdamW::clip_grad_norm`]. Gradients of the other kind (from another optimiser over
    /// the same parameters) are converted first.
    pub fn clip_grad_norm(&mut self, grads: &mut Gradients, max_norm: f64) -> Tensor {
        match (self, &mut *grads) {
            (Self::PerTensor(o), Gradients::PerTensor(g)) => o.clip_grad_norm(g, max_norm),
            // The views alias the flat buffer: scaling them scales it.
            (Self::PerTensor(o), Gradients::Flat(g)) => {
                o.clip_grad_norm(&mut g.per_param(), max_norm)
            }
            (Self::Flat(o), Gradients::Flat(g)) => o.clip_grad_norm(g, max_norm),
            (Self::Flat(o), Gradients::PerTensor(g)) => {
                let mut flat = o.gather(g);
                let norm = o.clip_grad_norm(&mut flat, max_norm);
                *grads = Gradients::Flat(flat);
                norm
            }
        }
    }

    /// See [`AdamW::step`].
    pub fn step(&mut self, grads: &Gradients, lr: f64) {
        match (self, grads) {
            (Self::PerTensor(o), Gradients::PerTensor(g)) => o.step(g, lr),
            (Self::PerTensor(o), Gradients::Flat(g)) => o.step(&g.per_param(), lr),
            (Self::Flat(o), Gradients::Flat(g)) => o.step(g, lr),
            (Self::Flat(o), Gradients::PerTensor(g)) => {
                let flat = o.gather(g);
                o.step(&flat, lr)
            }
        }
    }

    /// The AdamW state per parameter name (the parameters that have one): what checkpoints
    /// save as `exp_avg.<name>`, `exp_avg_sq.<name>` and the per-name step counts, the same for
    /// both optimisers, so that a run saved by one resumes on the other.
    pub fn state(&self) -> BTreeMap<String, ParamState> {
        match self {
            Self::PerTensor(o) => o
                .state
                .iter()
                .map(|(n, s)| {
                    let st = ParamState {
                        step: s.step,
                        exp_avg: s.exp_avg.shallow_clone(),
                        exp_avg_sq: s.exp_avg_sq.shallow_clone(),
                    };
                    (n.clone(), st)
                })
                .collect(),
            Self::Flat(o) => o.state(),
        }
    }

    /// Replaces the state by `state` (as [`Optimizer::state`] gives it), moving its tensors to
    /// the parameters' device.
    pub fn set_state(&mut self, state: BTreeMap<String, ParamState>) -> Result<(), OptimError> {
        match self {
            Self::PerTensor(o) => {
                let shapes: BTreeMap<&str, Vec<i64>> =
                    o.params.iter().map(|(n, p)| (n.as_str(), p.size())).collect();
                for (name, st) in &state {
                    let expected = shapes
                        .get(name.as_str())
                        .ok_or_else(|| OptimError::UnknownParameter(name.clone()))?;
                    for t in [&st.exp_avg, &st.exp_avg_sq] {
                        if t.size() != *expected {
                            return Err(OptimError::Shape {
                                name: name.clone(),
                                got: t.size(),
                                expected: expected.clone(),
                            });
                        }
                    }
                }
                let device = o.params.first().map(|(_, p)| p.device());
                o.state = state
                    .into_iter()
                    .map(|(n, s)| {
                        let to = |t: Tensor| match device {
                            Some(d) => t.to_device(d),
                            None => t,
                        };
                        let st = ParamState {
                            step: s.step,
                            exp_avg: to(s.exp_avg),
                            exp_avg_sq: to(s.exp_avg_sq),
                        };
                        (n, st)
                    })
                    .collect();
                Ok(())
            }
            Self::Flat(o) => o.set_state(&state),
        }
    }
}

/// One run's weights and optimiser state in the solo format: the reference `state_dict` names
/// and shapes, the per-parameter AdamW moments and step counts ([`AdamW::state`]). What a pack's
/// slot exports and imports (`pdt-pack`), and what a solo learner hands a pack.
#[derive(Debug)]
pub struct SlotState {
    pub weights: Vec<(String, Tensor)>,
    pub moments: BTreeMap<String, ParamState>,
}

impl SlotState {
    /// A copy of a solo model's weights (sorted by name) and its optimiser's state: never shared
    /// with the model it was read from.
    pub fn copy_of(vs: &tch::nn::VarStore, opt: &Optimizer) -> Self {
        tch::no_grad(|| {
            let mut weights: Vec<(String, Tensor)> =
                vs.variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
            weights.sort_by(|a, b| a.0.cmp(&b.0));
            let moments = opt
                .state()
                .iter()
                .map(|(n, st)| {
                    let copy = ParamState {
                        step: st.step,
                        exp_avg: st.exp_avg.copy(),
                        exp_avg_sq: st.exp_avg_sq.copy(),
                    };
                    (n.clone(), copy)
                })
                .collect();
            SlotState { weights, moments }
        })
    }
}

impl SlotState {
    /// Sets a solo model's weights (each by name and shape: every variable of `vs` given, none
    /// unknown) and its optimiser's state from this one; nothing is set when a name or shape is
    /// wrong. The error names the tensor.
    pub fn copy_into(self, vs: &tch::nn::VarStore, opt: &mut Optimizer) -> Result<(), String> {
        let vars = vs.variables();
        if let Some(name) = vars.keys().find(|k| !self.weights.iter().any(|(n, _)| n == *k)) {
            return Err(format!("no weights `{name}`"));
        }
        for (name, t) in &self.weights {
            match vars.get(name) {
                Some(v) if v.size() == t.size() => {}
                Some(v) => {
                    return Err(format!(
                        "`{name}` has shape {:?}, the model {:?}",
                        t.size(),
                        v.size()
                    ))
                }
                None => return Err(format!("unknown weights `{name}`")),
            }
        }
        tch::no_grad(|| {
            for (name, t) in &self.weights {
                if let Some(v) = vars.get(name) {
                    v.shallow_clone().copy_(t);
                }
            }
        });
        opt.set_state(self.moments).map_err(|e| e.to_string())
    }
}
