//! The exact engine: each slot an ordinary solo model (`PromptDt` and `crate::optim::Optimizer`),
//! stepped with the solo step (`crate::step::train_step`). A run trained through it is the same run
//! trained alone, bit for bit; it is the fallback for whatever the batched engine cannot pack, and
//! the reference the batched engine is tested against.
//!
//! On the CPU it steps the slots concurrently, one OS thread per slot for the pack's life
//! (`workers`), each with the run's libtorch threads ([`SoloThreads`]): a pack of N runs computes
//! as N processes of the same runs would (and keeps the cores as busy), with one copy of the data.
//! libtorch's generator is the process's, so each slot's dropout masks are drawn first, one slot
//! after another (seeded as the contract says, in the solo forward's order and shapes:
//! `PromptDt::draw_dropout`), and given to its step; on the CPU these are the bits the solo forward
//! draws itself (`pdt_model::dropout`). Elsewhere (CUDA, whose dropout kernel draws otherwise, or a
//! pack of one) the slots are stepped one after another, each drawing its own masks.

mod workers;

use super::engine::{PackEngine, PendingStep, SlotSpec, SlotState, SlotStep};
use crate::error::RunError;
use crate::optim::Optimizer;
use crate::step::{train_step_with, PendingStats, StepStats};
use crate::streams::STREAM_DROPOUT;
use pdt_base::seed::derive_seed;
use pdt_model::dropout::{Dropout, DropoutMasks};
use pdt_model::PromptDt;
use std::collections::BTreeMap;
use tch::{nn::VarStore, Device, Tensor};
use workers::Worker;

/// One run of the pack: its model and optimiser, as a solo run holds them.
struct Slot {
    spec: SlotSpec,
    vs: VarStore,
    model: PromptDt,
    opt: Optimizer,
}

impl Slot {
    /// The solo step; `dropout` is [`Dropout::Draw`] (seeded by the caller) or masks drawn for it.
    /// Its statistics are left unread (a worker reads them on its own thread).
    fn step(&mut self, input: &SlotStep, dropout: Dropout<'_>) -> PendingStats {
        let (batch, loss_on) = (&input.batch, self.spec.loss_on);
        train_step_with(&self.model, &mut self.opt, batch, loss_on, input.step, dropout)
    }

    fn state(&self) -> SlotState {
        SlotState::copy_of(&self.vs, &self.opt)
    }

    /// Sets the weights and optimiser state (slot `slot` of the pack, for the errors).
    fn import(&mut self, slot: usize, state: SlotState) -> Result<(), RunError> {
        let vars = self.vs.variables();
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
        self.opt
            .set_state(state.moments)
            .map_err(|e| RunError::Invalid(format!("pack engine: slot {slot}: {e}")))
    }
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

/// Where the slots live: here (stepped one after another) or each on its worker thread.
enum Slots {
    Here(Vec<Slot>),
    Workers(Vec<Worker>),
}

/// Dropout masks drawn ahead for a slot's next step, and what they were drawn for.
struct Ahead {
    /// The gradient step whose stream they come from.
    step: u64,
    /// The batch size and token count of the forward they fit.
    batch: i64,
    len: i64,
    masks: DropoutMasks,
}

/// N solo models, stepped at once in threads or one after another ([`SoloThreads`]).
pub struct SoloEngine {
    /// The slots' specs (the workers own the slots themselves).
    specs: Vec<SlotSpec>,
    slots: Slots,
    threads: SoloThreads,
    device: Device,
    /// Per slot (workers only), the masks of its next step, drawn while the workers compute this
    /// one: the draws (one slot after another on libtorch's one generator) are then off the
    /// step's critical path. A run's next step is its step + 1 with the same shapes unless it
    /// left or resumed elsewhere; masks that do not fit are drawn again.
    ahead: Vec<Option<Ahead>>,
}

impl SoloEngine {
    /// One slot per spec on `device`. Building a model draws its initial weights from libtorch's
    /// generator: call it with `crate::streams::torch_rng_lock` held. The weights drawn here are
    /// placeholders: each run imports its own (its seed's initialisation or its checkpoint)
    /// before its first step.
    /// The slots are stepped one after another ([`Self::with_threads`] to step them at once).
    pub fn new(specs: Vec<SlotSpec>, device: Device) -> Self {
        let threads = SoloThreads { concurrent: false, intra_op: 1 };
        let slots = Slots::Here(specs.iter().map(|s| new_slot(s, device)).collect());
        let ahead = specs.iter().map(|_| None).collect();
        Self { specs, slots, threads, device, ahead }
    }

    /// [`Self::new`], stepping the slots as `threads` says: concurrent (only on the CPU, where the
    /// dropout masks drawn beforehand are the solo forward's bits), each slot on its own thread
    /// from now until the engine is dropped.
    pub fn with_threads(
        specs: Vec<SlotSpec>,
        device: Device,
        threads: SoloThreads,
    ) -> Result<Self, RunError> {
        let mut engine = Self::new(specs, device);
        engine.threads =
            SoloThreads { concurrent: threads.concurrent && device == Device::Cpu, ..threads };
        if engine.threads.concurrent {
            let Slots::Here(slots) = std::mem::replace(&mut engine.slots, Slots::Here(Vec::new()))
            else {
                return Err(RunError::Invalid("pack engine: slots already on threads".into()));
            };
            let workers = slots
                .into_iter()
                .enumerate()
                .map(|(i, slot)| Worker::start(i, slot, engine.threads.intra_op))
                .collect::<Result<Vec<_>, _>>()?;
            engine.slots = Slots::Workers(workers);
        }
        Ok(engine)
    }

    /// How the slots are stepped.
    pub fn threads(&self) -> SoloThreads {
        self.threads
    }

    fn check(&self, slot: usize) -> Result<(), RunError> {
        if slot < self.specs.len() {
            Ok(())
        } else {
            Err(RunError::Invalid(format!(
                "pack engine: slot {slot} out of range (the pack has {} runs)",
                self.specs.len()
            )))
        }
    }
}

fn new_slot(spec: &SlotSpec, device: Device) -> Slot {
    let vs = VarStore::new(device);
    let mut model = PromptDt::new(&vs.root(), &spec.model);
    model.set_last_block(crate::step::last_block(spec.last_block, device, false));
    let opt = Optimizer::new(&vs, &spec.model.parameter_names(), spec.optim.clone());
    Slot { spec: spec.clone(), vs, model, opt }
}

/// The seed of the slot's dropout stream for this step (the engine contract).
fn dropout_seed(spec: &SlotSpec, input: &SlotStep) -> i64 {
    derive_seed(spec.seed, STREAM_DROPOUT, input.step) as i64
}

/// Refuses a batch with a prompt for a run without one, or the other way round.
fn check_prompt(i: usize, spec: &SlotSpec, input: &SlotStep) -> Result<(), RunError> {
    if input.batch.prompt.is_some() != spec.uses_prompt {
        return Err(RunError::Invalid(format!(
            "pack engine: slot {i}'s batch {} a prompt, but its run {}",
            if input.batch.prompt.is_some() { "has" } else { "lacks" },
            if spec.uses_prompt { "uses one" } else { "uses none" }
        )));
    }
    Ok(())
}

/// Slot `spec`'s masks for its gradient step `step`: a forward of `batch` sequences of `len` tokens.
/// Seeds libtorch's generator (the caller holds it).
fn draw_masks(spec: &SlotSpec, step: u64, batch: i64, len: i64, device: Device) -> DropoutMasks {
    tch::manual_seed(derive_seed(spec.seed, STREAM_DROPOUT, step) as i64);
    DropoutMasks::draw(&spec.model, batch, len, device)
}

impl SoloEngine {
    /// Starts `slot`'s step on its worker: its masks (drawn ahead when they fit) handed over, then
    /// the masks of its next step drawn while the worker computes. The caller holds libtorch's
    /// generator (`crate::streams::torch_rng_lock`).
    fn start_on_worker(&mut self, slot: usize, input: SlotStep) -> Result<PendingStep, RunError> {
        self.check(slot)?;
        let Slots::Workers(workers) = &self.slots else {
            return Err(RunError::Invalid("pack engine: the runs are not on threads".into()));
        };
        let spec = &self.specs[slot];
        check_prompt(slot, spec, &input)?;
        let (h, p) = (&input.batch.history, input.batch.prompt.as_ref());
        let (batch, len) = (h.batch_size(), PromptDt::token_count(h, p));
        let masks = match self.ahead[slot].take() {
            Some(a) if (a.step, a.batch, a.len) == (input.step, batch, len) => a.masks,
            _ => draw_masks(spec, input.step, batch, len, self.device),
        };
        let step = input.step + 1;
        let pending = workers[slot].step(input, masks)?;
        let masks = draw_masks(spec, step, batch, len, self.device);
        self.ahead[slot] = Some(Ahead { step, batch, len, masks });
        Ok(pending)
    }
}

impl PackEngine for SoloEngine {
    fn slots(&self) -> usize {
        self.specs.len()
    }

    fn step(
        &mut self,
        steps: Vec<Option<SlotStep>>,
    ) -> Result<Vec<Option<PendingStats>>, RunError> {
        if steps.len() != self.specs.len() {
            return Err(RunError::Invalid(format!(
                "pack engine: {} slot inputs for a pack of {} runs",
                steps.len(),
                self.specs.len()
            )));
        }
        for (i, (spec, input)) in self.specs.iter().zip(&steps).enumerate() {
            if let Some(input) = input {
                check_prompt(i, spec, input)?;
            }
        }
        if let Slots::Here(slots) = &mut self.slots {
            return Ok(slots
                .iter_mut()
                .zip(steps)
                .map(|(slot, input)| {
                    let input = input?;
                    // The contract's dropout stream: the solo learner seeds the same.
                    tch::manual_seed(dropout_seed(&slot.spec, &input));
                    Some(slot.step(&input, Dropout::Draw))
                })
                .collect());
        }
        // On the workers: every slot's step started (one after another: their masks come from
        // the one generator), then every result awaited before any error is returned.
        let mut pending = Vec::with_capacity(steps.len());
        for (i, input) in steps.into_iter().enumerate() {
            pending.push(input.map(|input| self.start_on_worker(i, input)));
        }
        let done: Vec<Option<Result<StepStats, RunError>>> =
            pending.into_iter().map(|p| p.map(|p| p.and_then(PendingStep::wait))).collect();
        let done: Vec<Option<StepStats>> =
            done.into_iter().map(Option::transpose).collect::<Result<_, _>>()?;
        Ok(done.into_iter().map(|st| st.map(PendingStats::ready)).collect())
    }

    fn export(&self, slot: usize) -> Result<SlotState, RunError> {
        self.check(slot)?;
        match &self.slots {
            Slots::Here(slots) => Ok(slots[slot].state()),
            Slots::Workers(workers) => workers[slot].export(),
        }
    }

    fn import(&mut self, slot: usize, state: SlotState) -> Result<(), RunError> {
        self.check(slot)?;
        match &mut self.slots {
            Slots::Here(slots) => slots[slot].import(slot, state),
            Slots::Workers(workers) => workers[slot].import(state),
        }
    }

    fn steps_alone(&self) -> bool {
        matches!(self.slots, Slots::Workers(_))
    }

    fn start(&mut self, slot: usize, step: SlotStep) -> Result<PendingStep, RunError> {
        self.start_on_worker(slot, step)
    }
}
