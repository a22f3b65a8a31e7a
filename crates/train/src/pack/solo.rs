//! The exact engine: each slot an ordinary solo model (`PromptDt` and `crate::optim::Optimizer`),
//! stepped with the solo step (`crate::step::train_step`). A run trained through it is the same run
//! trained alone, bit for bit; it is the fallback for whatever the batched engine cannot pack, and
//! the reference the batched engine is tested against.
//!
//! On the CPU it steps the slots concurrently, one OS thread per slot, each with the run's libtorch
//! threads ([`SoloThreads`]): a pack of N runs computes as N processes of the same runs would (and
//! keeps the cores as busy), with one copy of the data. libtorch's generator is the process's, so each slot's dropout masks are drawn
//! first, one slot after another (seeded as the contract says, in the solo forward's order and
//! shapes: `PromptDt::draw_dropout`), and given to its step; on the CPU these are the bits the solo
//! forward draws itself (`pdt_model::dropout`). Elsewhere (CUDA, whose dropout kernel draws
//! otherwise, or a pack of one) the slots are stepped one after another, each drawing its masks.

use super::engine::{PackEngine, SlotSpec, SlotState, SlotStep};
use crate::error::RunError;
use crate::optim::Optimizer;
use crate::step::{train_step, train_step_with, StepStats};
use crate::streams::STREAM_DROPOUT;
use pdt_base::seed::derive_seed;
use pdt_model::dropout::{Dropout, DropoutMasks};
use pdt_model::PromptDt;
use std::collections::BTreeMap;
use tch::{nn::VarStore, Device, Tensor};

/// One run of the pack: its model and optimiser, as a solo run holds them.
struct Slot {
    spec: SlotSpec,
    vs: VarStore,
    model: PromptDt,
    opt: Optimizer,
}

/// How the solo engine uses the CPU's threads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SoloThreads {
    /// The slots of a step run at once, one OS thread each.
    pub concurrent: bool,
    /// libtorch intra-op threads of each slot's step (each worker's, when concurrent).
    pub intra_op: usize,
}

// libtorch's results depend on its intra-op thread count (its kernels split their work, and so
// their sums, by thread), even on small tensors: a run is bit for bit its solo self only with the
// solo run's count. So each worker gets the run's `threads`, not a share of the cores.

impl SoloThreads {
    /// For a pack of `slots` runs with `threads` libtorch threads per run (the pack's
    /// `run.threads`, resolved: 0 is every core) on `device`: on the CPU with at least 2 runs,
    /// their steps at once, each with `threads` libtorch threads, as N processes of these runs
    /// would compute them (the OS shares the cores among them the same way: to keep a pack within
    /// C cores, give its runs `threads = C / N`). Otherwise (a pack of one, CUDA) one step after
    /// another.
    pub fn for_pack(device: Device, threads: usize, slots: usize) -> Self {
        let concurrent = device == Device::Cpu && slots >= 2;
        SoloThreads { concurrent, intra_op: threads.max(1) }
    }
}

/// N solo models, stepped at once in threads or one after another ([`SoloThreads`]).
pub struct SoloEngine {
    slots: Vec<Slot>,
    threads: SoloThreads,
}

impl SoloEngine {
    /// One slot per spec on `device`. Building a model draws its initial weights from libtorch's
    /// generator: call it with `crate::streams::torch_rng_lock` held. The weights drawn here are
    /// placeholders: each run imports its own (its seed's initialisation or its checkpoint)
    /// before its first step.
    /// The slots are stepped one after another ([`Self::with_threads`] to step them at once).
    pub fn new(specs: Vec<SlotSpec>, device: Device) -> Self {
        Self::with_threads(specs, device, SoloThreads { concurrent: false, intra_op: 1 })
    }

    /// [`Self::new`], stepping the slots as `threads` says (concurrent only on the CPU: the
    /// dropout masks drawn beforehand are the solo forward's bits there alone).
    pub fn with_threads(specs: Vec<SlotSpec>, device: Device, threads: SoloThreads) -> Self {
        let threads =
            SoloThreads { concurrent: threads.concurrent && device == Device::Cpu, ..threads };
        let slots = specs
            .into_iter()
            .map(|spec| {
                let vs = VarStore::new(device);
                let model = PromptDt::new(&vs.root(), &spec.model);
                let opt = Optimizer::new(&vs, &spec.model.parameter_names(), spec.optim.clone());
                Slot { spec, vs, model, opt }
            })
            .collect();
        Self { slots, threads }
    }

    /// How the slots are stepped.
    pub fn threads(&self) -> SoloThreads {
        self.threads
    }

    fn slot(&self, slot: usize) -> Result<&Slot, RunError> {
        self.slots.get(slot).ok_or_else(|| no_slot(slot, self.slots.len()))
    }
}

/// The seed of the slot's dropout stream for this step (the engine contract).
fn dropout_seed(slot: &Slot, input: &SlotStep) -> i64 {
    derive_seed(slot.spec.seed, STREAM_DROPOUT, input.step) as i64
}

/// Refuses a batch with a prompt for a run without one, or the other way round.
fn check_prompt(i: usize, slot: &Slot, input: &SlotStep) -> Result<(), RunError> {
    if input.batch.prompt.is_some() != slot.spec.uses_prompt {
        return Err(RunError::Invalid(format!(
            "pack engine: slot {i}'s batch {} a prompt, but its run {}",
            if input.batch.prompt.is_some() { "has" } else { "lacks" },
            if slot.spec.uses_prompt { "uses one" } else { "uses none" }
        )));
    }
    Ok(())
}

/// One step of every slot given an input, at once: each slot's masks drawn in turn (the caller
/// holds libtorch's generator, `crate::streams::torch_rng_lock`), then each slot's forward,
/// backward and update on its own thread with `intra_op` libtorch threads, drawing nothing.
fn step_concurrently(
    slots: &mut [Slot],
    steps: Vec<Option<SlotStep>>,
    intra_op: usize,
) -> Result<Vec<Option<StepStats>>, RunError> {
    let work: Vec<Option<(SlotStep, DropoutMasks)>> = slots
        .iter()
        .zip(steps)
        .map(|(slot, input)| {
            input.map(|input| {
                tch::manual_seed(dropout_seed(slot, &input));
                let b = &input.batch;
                let masks = slot.model.draw_dropout(&b.history, b.prompt.as_ref());
                (input, masks)
            })
        })
        .collect();
    let intra_op = i32::try_from(intra_op).unwrap_or(i32::MAX);
    let results: Vec<Option<std::thread::Result<StepStats>>> = std::thread::scope(|scope| {
        let handles: Vec<_> = slots
            .iter_mut()
            .zip(work)
            .map(|(slot, work)| {
                // Each worker owns its inputs (a tensor may move to another thread, not be shared).
                let (input, masks) = work?;
                Some(scope.spawn(move || {
                    // libtorch's intra-op thread count is per OS thread (OpenMP's): set on each
                    // worker (it also sets the process default, the same for every worker).
                    tch::set_num_threads(intra_op);
                    let Slot { model, opt, spec, .. } = slot;
                    let given = Dropout::Given(&masks);
                    train_step_with(model, opt, &input.batch, spec.loss_on, input.step, given)
                }))
            })
            .collect();
        handles.into_iter().map(|h| h.map(|h| h.join())).collect()
    });
    results
        .into_iter()
        .enumerate()
        .map(|(i, r)| match r {
            None => Ok(None),
            Some(Ok(st)) => Ok(Some(st)),
            Some(Err(_)) => {
                Err(RunError::Invalid(format!("pack engine: slot {i}'s step panicked (see above)")))
            }
        })
        .collect()
}

fn no_slot(slot: usize, n: usize) -> RunError {
    RunError::Invalid(format!("pack engine: slot {slot} out of range (the pack has {n} runs)"))
}

impl PackEngine for SoloEngine {
    fn slots(&self) -> usize {
        self.slots.len()
    }

    fn step(&mut self, steps: Vec<Option<SlotStep>>) -> Result<Vec<Option<StepStats>>, RunError> {
        if steps.len() != self.slots.len() {
            return Err(RunError::Invalid(format!(
                "pack engine: {} slot inputs for a pack of {} runs",
                steps.len(),
                self.slots.len()
            )));
        }
        for (i, (slot, input)) in self.slots.iter().zip(&steps).enumerate() {
            if let Some(input) = input {
                check_prompt(i, slot, input)?;
            }
        }
        if self.threads.concurrent {
            return step_concurrently(&mut self.slots, steps, self.threads.intra_op);
        }
        let mut out = Vec::with_capacity(steps.len());
        for (slot, input) in self.slots.iter_mut().zip(steps) {
            let Some(input) = input else {
                out.push(None);
                continue;
            };
            // The contract's dropout stream: the solo learner seeds the same before its step.
            tch::manual_seed(dropout_seed(slot, &input));
            let st =
                train_step(&slot.model, &mut slot.opt, &input.batch, slot.spec.loss_on, input.step);
            out.push(Some(st));
        }
        Ok(out)
    }

    fn export(&self, slot: usize) -> Result<SlotState, RunError> {
        let s = self.slot(slot)?;
        Ok(SlotState::copy_of(&s.vs, &s.opt))
    }

    fn import(&mut self, slot: usize, state: SlotState) -> Result<(), RunError> {
        let n = self.slots.len();
        let s = self.slots.get_mut(slot).ok_or_else(|| no_slot(slot, n))?;
        let vars = s.vs.variables();
        let given: BTreeMap<&str, &Tensor> =
            state.weights.iter().map(|(k, t)| (k.as_str(), t)).collect();
        if let Some(name) = vars.keys().find(|k| !given.contains_key(k.as_str())) {
            return Err(RunError::Invalid(format!(
                "pack engine: slot {slot}: no weights `{name}`"
            )));
        }
        for (name, t) in &given {
            let var = vars.get(*name).ok_or_else(|| {
                RunError::Invalid(format!("pack engine: slot {slot}: unknown weights `{name}`"))
            })?;
            if var.size() != t.size() {
                return Err(RunError::Invalid(format!(
                    "pack engine: slot {slot}: `{name}` has shape {:?}, the model {:?}",
                    t.size(),
                    var.size()
                )));
            }
        }
        tch::no_grad(|| {
            for (name, t) in &given {
                if let Some(var) = vars.get(*name) {
                    var.shallow_clone().copy_(t);
                }
            }
        });
        s.opt
            .set_state(state.moments)
            .map_err(|e| RunError::Invalid(format!("pack engine: slot {slot}: {e}")))?;
        Ok(())
    }
}
