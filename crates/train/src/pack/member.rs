//! One run of a pack, as the run loop sees it: a [`Learner`] whose gradient steps go through the
//! pack's [`Hub`], and whose evaluations and files go through an ordinary solo
//! [`PromptDtLearner`] holding a copy of the run's slot. So everything but the step (sampling,
//! evaluation, MT-BC-Finetune's fine-tuning, checkpoint files, resume) is the solo code.

use super::engine::SlotStep;
use super::hub::Hub;
use crate::error::RunError;
use crate::methods::prompt_dt::{checked, iteration_metrics, PromptDtLearner, Variant};
use crate::methods::{
    CheckpointFiles, IterationAt, IterationMetrics, Learner, SavedSteps, TaskEval,
};
use crate::setup::{Setup, Split};
use crate::step::DeviceBatch;
use crate::streams::torch_rng_lock;
use pdt_model::Segments;
use pdt_prompt::Rng;
use std::cell::{Cell, RefCell};
use std::path::Path;

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
}

impl<'s> PackMember<'s> {
    /// The run's learner initialised from its seed, as a solo run's, and its weights given to the
    /// engine's slot.
    pub(crate) fn new(setup: &'s Setup, slot: usize, hub: &'s Hub) -> Result<Self, RunError> {
        let variant = Variant::of(setup.cfg.run.method);
        let solo = {
            let _rng = torch_rng_lock();
            PromptDtLearner::new(setup, variant)?
        };
        hub.import(slot, solo.state())?;
        let (solo, synced) = (RefCell::new(solo), Cell::new(true));
        Ok(Self { setup, slot, hub, solo, synced, last_step: None })
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

/// A second handle on `b`'s tensors (nothing writes to a batch once it is built).
fn alias(b: &DeviceBatch) -> DeviceBatch {
    let seg = |s: &Segments| Segments {
        states: s.states.shallow_clone(),
        actions: s.actions.shallow_clone(),
        returns_to_go: s.returns_to_go.shallow_clone(),
        timesteps: s.timesteps.shallow_clone(),
        mask: s.mask.shallow_clone(),
    };
    DeviceBatch { history: seg(&b.history), prompt: b.prompt.as_ref().map(seg) }
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
        // Each step's batch is sampled while the pack takes the previous step (the engine runs
        // on whichever run waits first): the sampler draws the same batches in the same order as
        // the solo loop, and none beyond the iteration's last step, so its stream stands where
        // the solo run's does at every checkpoint.
        let end = at.first_step + at.steps;
        let mut next = (at.steps > 0).then(|| solo.sample_batch(rng));
        let stats = at.each_step(|step| {
            let batch = next.take().ok_or_else(|| {
                RunError::Invalid(format!("pack slot {slot}: no batch for step {step}"))
            })?;
            if finetune {
                last = Some((step, alias(&batch)));
            }
            hub.submit(slot, SlotStep { step, batch })?;
            if step + 1 < end {
                next = Some(solo.sample_batch(rng));
            }
            let st = hub.wait(slot)?;
            checked(at, cfg, step, st)
        })?;
        drop(solo);
        self.last_step = last;
        Ok(iteration_metrics(&stats))
    }

    fn evaluate(&mut self, split: Split, rng: &mut Rng) -> Result<Vec<TaskEval>, RunError> {
        self.sync()?;
        let mut solo = self.solo.borrow_mut();
        if solo.variant().finetune && split == Split::Test {
            // Fine-tuning draws its dropout from libtorch's generator where the run's last step
            // left it: that state restored, and no other run's draw between it and the tuning.
            let _rng = torch_rng_lock();
            if let Some((step, batch)) = &self.last_step {
                solo.redraw_step_dropout(*step, batch);
            }
            return solo.evaluate(split, rng);
        }
        solo.evaluate(split, rng)
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
