//! One run of a pack, as the run loop sees it: a [`Learner`] whose gradient steps go through the
//! pack's [`Hub`], and whose evaluations and files go through an ordinary solo
//! [`PromptDtLearner`] holding a copy of the run's slot. So everything but the step (sampling,
//! evaluation, MT-BC-Finetune's fine-tuning, checkpoint files, resume) is the solo code. With an
//! engine that acts for its runs (the batched one), a plain evaluation's forwards are the engine's,
//! computed with the other evaluating runs' through the hub (`PackActor`); the episodes around them
//! are still the solo evaluation's.

use super::engine::{SlotAct, SlotStep};
use super::hub::Hub;
use crate::config::TestTime;
use crate::error::RunError;
use crate::methods::prompt_dt::{read_iteration, PromptDtLearner, TuneTurns, Variant};
use crate::methods::{
    CheckpointFiles, Evaluation, IterationAt, IterationMetrics, Learner, SavedSteps,
};
use crate::setup::{Setup, Split};
use crate::step::DeviceBatch;
use crate::streams::torch_rng_lock;
use pdt_eval::{ActRows, EvalError};
use pdt_model::device::GeneratorState;
use pdt_model::Segments;
use pdt_prompt::Rng;
use std::cell::{Cell, RefCell};
use std::path::Path;
use tch::Tensor;

/// The sample counts of a pack's evaluation forwards, one per split: the most episodes any run of
/// the pack has running in one forward (its tasks x `eval.episodes`, at most `eval.max_batch`).
/// Fixed for the pack, so that a run's actions never depend on which other runs act with it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ActShape {
    pub(crate) test_rows: i64,
    pub(crate) train_rows: i64,
}

impl ActShape {
    fn rows(self, split: Split) -> i64 {
        match split {
            Split::Test => self.test_rows,
            Split::Train => self.train_rows,
        }
    }
}

/// A run's evaluation forwards, computed by the pack's engine with the other runs' ([`Hub::act`]).
struct PackActor<'h> {
    hub: &'h Hub,
    slot: usize,
    rows: i64,
}

impl ActRows for PackActor<'_> {
    fn act_rows(&self, history: &Segments, prompt: Option<&Segments>) -> Result<Tensor, EvalError> {
        let act = SlotAct {
            history: history.shallow_clone(),
            prompt: prompt.map(Segments::shallow_clone),
            rows: self.rows,
        };
        self.hub.act(self.slot, act).map_err(|e| EvalError::Acting(e.to_string()))
    }
}

/// A run of a pack (slot `slot` of `hub`'s engine).
pub(crate) struct PackMember<'s> {
    setup: &'s Setup,
    slot: usize,
    hub: &'s Hub,
    /// The run as a solo learner: its sampler, evaluation and files. Its weights and optimiser
    /// state are the slot's whenever `synced`.
    /// (In cells: the run loop saves through `&self`.)
    solo: RefCell<PromptDtLearner<'s>>,
    synced: Cell<bool>,
    /// MT-BC-Finetune: the last gradient step and its batch, to put libtorch's generator where
    /// the solo run leaves it before fine-tuning (`PromptDtLearner::redraw_step_dropout`).
    last_step: Option<(u64, DeviceBatch)>,
    /// The engine's evaluation forwards' shape, when it acts for the pack's runs.
    act: Option<ActShape>,
}

impl<'s> PackMember<'s> {
    /// The run's learner initialised from its seed, as a solo run's, and its weights given to the
    /// engine's slot.
    pub(crate) fn new(
        setup: &'s Setup,
        slot: usize,
        hub: &'s Hub,
        act: Option<ActShape>,
    ) -> Result<Self, RunError> {
        let variant = Variant::of(setup.cfg.run.method);
        let solo = {
            let _rng = torch_rng_lock();
            PromptDtLearner::new(setup, variant)?
        };
        hub.import(slot, solo.state())?;
        let (solo, synced) = (RefCell::new(solo), Cell::new(true));
        Ok(Self { setup, slot, hub, solo, synced, last_step: None, act })
    }

    /// The solo learner given the slot's current weights and optimiser state.
    fn sync(&self) -> Result<(), RunError> {
        if !self.synced.get() {
            self.solo.borrow_mut().set_state(self.hub.export(self.slot)?)?;
            self.synced.set(true);
        }
        Ok(())
    }
}

impl Learner for PackMember<'_> {
    fn loss_metric(&self) -> &'static str {
        self.solo.borrow().loss_metric()
    }

    fn state_tag(&self) -> Option<&'static str> {
        self.solo.borrow().state_tag()
    }

    fn check_can_train(&self) -> Result<(), RunError> {
        self.solo.borrow().check_can_train()
    }

    fn train_iteration(
        &mut self,
        at: IterationAt<'_>,
        rng: &mut Rng,
    ) -> Result<IterationMetrics, RunError> {
        let cfg = &self.setup.cfg;
        let solo = self.solo.borrow();
        let finetune = solo.variant().finetune;
        self.synced.set(false);
        let (hub, slot) = (self.hub, self.slot);
        let mut last = None;
        // Each step's batch is sampled while the pack takes the previous step (on the pack's
        // stepper thread, `Hub::stepper`): the sampler draws the same batches in the same order as
        // the solo loop, and none beyond the iteration's last step, so its stream stands where
        // the solo run's does at every checkpoint.
        let end = at.first_step + at.steps;
        let mut next = (at.steps > 0).then(|| solo.sample_batch(rng));
        let stats = at.each_step(|step| {
            let batch = next.take().ok_or_else(|| {
                RunError::Invalid(format!("pack slot {slot}: no batch for step {step}"))
            })?;
            if finetune {
                last = Some((step, batch.shallow_clone()));
            }
            hub.submit(slot, SlotStep { step, batch })?;
            if step + 1 < end {
                next = Some(solo.sample_batch(rng));
            }
            hub.wait(slot)
        })?;
        drop(solo);
        self.last_step = last;
        read_iteration(at, cfg, stats)
    }

    fn evaluate(
        &mut self,
        split: Split,
        test_time: &TestTime,
        rng: &mut Rng,
    ) -> Result<Evaluation, RunError> {
        self.sync()?;
        let mut solo = self.solo.borrow_mut();
        // The engine acts for the pack's runs (the batched one): the plain evaluation's forwards
        // are computed with those of the other runs evaluating at the same time. (Not bit for
        // bit the solo model's: the pack's weights are within its tolerance of the solo run's,
        // and its forward is the full one, not `eval.inference = "cached"`.)
        if let Some(shape) = self.act.filter(|_| solo.evaluates_plainly(split)) {
            let _acting = self.hub.acting(self.slot);
            let actor = PackActor { hub: self.hub, slot: self.slot, rows: shape.rows(split) };
            return solo.evaluate_through(split, rng, &actor);
        }
        if solo.variant().finetune && split == Split::Test {
            // Fine-tuning draws its dropout from libtorch's generator where the run's last step
            // left it: that state restored, then kept between the test tasks' tunings, each in its
            // turn at the generator. The episodes run without it, so the pack's other runs (its
            // other fine-tuning runs too) step and evaluate meanwhile. (Holding the generator for
            // the whole evaluation made a pack's fine-tuning runs evaluate one after another.)
            let state = {
                let _rng = torch_rng_lock();
                if let Some((step, batch)) = &self.last_step {
                    solo.redraw_step_dropout(*step, batch);
                }
                GeneratorState::take(self.setup.device).map_err(generator_error)?
            };
            let turns = InTurns { state: RefCell::new(state), device: self.setup.device };
            return solo.evaluate_in_turns(split, test_time, rng, &turns);
        }
        solo.evaluate(split, test_time, rng)
    }

    fn save(&self, files: &CheckpointFiles) -> Result<serde_json::Value, RunError> {
        self.sync()?;
        self.solo.borrow().save(files)
    }

    fn load(&mut self, files: &CheckpointFiles, saved: SavedSteps<'_>) -> Result<(), RunError> {
        let mut solo = self.solo.borrow_mut();
        solo.load(files, saved)?;
        self.hub.import(self.slot, solo.state())?;
        self.synced.set(true);
        Ok(())
    }

    fn load_weights(&mut self, path: &Path) -> Result<(), RunError> {
        let mut solo = self.solo.borrow_mut();
        solo.load_weights(path)?;
        self.hub.import(self.slot, solo.state())?;
        self.synced.set(true);
        Ok(())
    }
}

/// A packed run's turns at libtorch's generator for its fine-tuning: each holds the generator with
/// the state the previous turn left (`pdt_model::device::GeneratorState`).
struct InTurns {
    state: RefCell<GeneratorState>,
    device: tch::Device,
}

impl TuneTurns for InTurns {
    fn turn(&self, tune: &mut dyn FnMut() -> Result<(), RunError>) -> Result<(), RunError> {
        let _rng = torch_rng_lock();
        self.state.borrow().restore().map_err(generator_error)?;
        tune()?;
        *self.state.borrow_mut() = GeneratorState::take(self.device).map_err(generator_error)?;
        Ok(())
    }
}

fn generator_error(e: String) -> RunError {
    RunError::Invalid(format!("libtorch's random generator: {e}"))
}
