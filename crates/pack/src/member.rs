//! One run of a pack, as the run loop sees it: a [`Learner`] whose gradient steps go through the
//! pack's [`Hub`], and whose everything else (sampling, evaluation, MT-BC-Finetune's fine-tuning,
//! checkpoint files, resume) is its method's own learner, a [`Steppable`] from the registry.
//!
//! One owner for the run's weights and optimiser state: the learner. The engine holds them while
//! the run trains: they are handed to the engine's slot before a step when the learner's have
//! changed (a fresh run, a load), and taken back before anything reads them (an evaluation, a
//! save). Each hand-over is a `&mut` call of the run loop's, so the member always knows which side
//! holds the current state (`at_engine`).

use crate::engine::SlotStep;
use crate::hub::Hub;
use pdt_prompt::Rng;
use pdt_rundir::config::TestTime;
use pdt_train::methods::{
    read_iteration, CheckpointFiles, Evaluation, IterationAt, IterationMetrics, Learner,
    SavedSteps, Steppable,
};
use pdt_train::run::RunError;
use pdt_train::setup::{Setup, Split};
use pdt_train::step::DeviceBatch;
use pdt_train::streams::torch_rng_lock;
use std::path::Path;

/// Which side holds a run's current weights and optimiser state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Holder {
    /// The learner's are current; the engine's slot may be stale.
    Learner,
    /// The engine's slot is current (steps were taken since); the learner's are stale.
    Engine,
    /// Both hold the same (just handed over).
    Both,
}

/// A run of a pack (slot `slot` of `hub`'s engine).
pub(crate) struct PackMember<'s> {
    setup: &'s Setup,
    slot: usize,
    hub: &'s Hub,
    learner: Box<dyn Steppable + 's>,
    at_engine: Holder,
    /// The last gradient step and its batch, for an evaluation that draws from libtorch's
    /// generator where that step left it (`Steppable::replay_step_draws`).
    last_step: Option<(u64, DeviceBatch)>,
}

impl<'s> PackMember<'s> {
    /// The run's learner initialised from its seed, as a solo run's (refused by name if its
    /// method does not pack).
    pub(crate) fn new(setup: &'s Setup, slot: usize, hub: &'s Hub) -> Result<Self, RunError> {
        let learner = {
            let _rng = torch_rng_lock();
            pdt_train::methods::steppable(setup)?
        };
        Ok(Self { setup, slot, hub, learner, at_engine: Holder::Learner, last_step: None })
    }

    /// The learner's state handed to the engine's slot, unless the slot already holds it.
    fn hand_to_engine(&mut self) -> Result<(), RunError> {
        if self.at_engine == Holder::Learner {
            self.hub.import(self.slot, self.learner.export())?;
            self.at_engine = Holder::Both;
        }
        Ok(())
    }

    /// The engine slot's state taken back into the learner, unless the learner holds it.
    fn take_back(&mut self) -> Result<(), RunError> {
        if self.at_engine == Holder::Engine {
            self.learner.import(self.hub.export(self.slot)?)?;
            self.at_engine = Holder::Both;
        }
        Ok(())
    }
}

impl Learner for PackMember<'_> {
    fn loss_metric(&self) -> &'static str {
        self.learner.loss_metric()
    }

    fn state_tag(&self) -> Option<&'static str> {
        self.learner.state_tag()
    }

    fn check_can_train(&self) -> Result<(), RunError> {
        self.learner.check_can_train()
    }

    fn train_iteration(
        &mut self,
        at: IterationAt<'_>,
        rng: &mut Rng,
    ) -> Result<IterationMetrics, RunError> {
        self.hand_to_engine()?;
        self.at_engine = Holder::Engine;
        let (hub, slot, learner) = (self.hub, self.slot, &*self.learner);
        let mut last = None;
        // Each step's batch is sampled while the pack takes the previous step (on the pack's
        // stepper thread, `Hub::stepper`): the sampler draws the same batches in the same order as
        // the solo loop, and none beyond the iteration's last step, so its stream stands where
        // the solo run's does at every checkpoint.
        let end = at.first_step + at.steps;
        let mut next = (at.steps > 0).then(|| learner.sample_batch(rng));
        let stats = at.each_step(|step| {
            let batch = next.take().ok_or_else(|| {
                RunError::Internal(format!("pack slot {slot}: no batch for step {step}"))
            })?;
            last = Some((step, batch.shallow_clone()));
            hub.submit(slot, SlotStep { step, batch })?;
            if step + 1 < end {
                next = Some(learner.sample_batch(rng));
            }
            hub.wait(slot)
        })?;
        self.last_step = last.or(self.last_step.take());
        read_iteration(at, &self.setup.cfg, stats)
    }

    fn evaluate(
        &mut self,
        split: Split,
        test_time: &TestTime,
        rng: &mut Rng,
    ) -> Result<Evaluation, RunError> {
        self.take_back()?;
        let last = self.last_step.as_ref().map(|(s, b)| (*s, b));
        let rng_lock = torch_rng_lock();
        if self.learner.replay_step_draws(split, last) {
            // The evaluation draws from libtorch's generator (MT-BC-Finetune's fine-tuning), now
            // where the run's last step left it: held for the whole evaluation, so its draws are
            // the run's alone (the pack's other runs wait for it at their next step).
            return self.learner.evaluate(split, test_time, rng);
        }
        drop(rng_lock);
        self.learner.evaluate(split, test_time, rng)
    }

    fn save(&mut self, files: &CheckpointFiles) -> Result<serde_json::Value, RunError> {
        self.take_back()?;
        self.learner.save(files)
    }

    fn load(&mut self, files: &CheckpointFiles, saved: SavedSteps<'_>) -> Result<(), RunError> {
        self.learner.load(files, saved)?;
        self.at_engine = Holder::Learner;
        Ok(())
    }

    fn load_weights(&mut self, path: &Path) -> Result<(), RunError> {
        self.learner.load_weights(path)?;
        self.at_engine = Holder::Learner;
        Ok(())
    }
}
