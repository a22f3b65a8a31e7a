//! The exact engine: each slot an ordinary solo model (`PromptDt` and `pdt_train::optim::Optimizer`),
//! stepped with the solo step (`pdt_train::step::train_step`), one slot after another. A run trained
//! through it is the same run trained alone, bit for bit: it is the CPU's engine and the oracle the
//! batched engine is tested against. (On the CPU a pack of N runs so takes about the time of its
//! runs one after another; `reproduce --jobs` runs them as processes at once instead.)

use crate::engine::{PackEngine, SlotSpec, SlotStep};
use pdt_base::seed::derive_seed;
use pdt_model::dropout::Dropout;
use pdt_model::PromptDt;
use pdt_run::streams::STREAM_DROPOUT;
use pdt_train::optim::Optimizer;
use pdt_train::optim::SlotState;
use pdt_train::run::RunError;
use pdt_train::step::{train_step_with, PendingStats};
use tch::{nn::VarStore, Device};

/// One run of the pack: its model and optimiser, as a solo run holds them.
struct Slot {
    spec: SlotSpec,
    vs: VarStore,
    model: PromptDt,
    opt: Optimizer,
}

/// N solo models, stepped one after another.
pub struct SoloEngine {
    slots: Vec<Slot>,
}

impl SoloEngine {
    /// One slot per spec on `device`. Building a model draws its initial weights from libtorch's
    /// generator: call it with `pdt_train::streams::torch_rng_lock` held. The weights drawn here are
    /// placeholders: each run imports its own (its seed's initialisation or its checkpoint)
    /// before its first step.
    pub fn new(specs: Vec<SlotSpec>, device: Device) -> Self {
        let slots = specs
            .into_iter()
            .map(|spec| {
                let vs = VarStore::new(device);
                let mut model = PromptDt::new(&vs.root(), &spec.model);
                model.set_last_block(pdt_train::step::last_block(spec.last_block, device, false));
                let opt = Optimizer::new(&vs, &spec.model.parameter_names(), spec.optim.clone());
                Slot { spec, vs, model, opt }
            })
            .collect();
        Self { slots }
    }

    fn slot(&self, slot: usize) -> Result<&Slot, RunError> {
        self.slots.get(slot).ok_or_else(|| {
            RunError::Internal(format!(
                "pack engine: slot {slot} out of range (the pack has {} runs)",
                self.slots.len()
            ))
        })
    }
}

impl PackEngine for SoloEngine {
    fn slots(&self) -> usize {
        self.slots.len()
    }

    fn step(
        &mut self,
        steps: Vec<Option<SlotStep>>,
    ) -> Result<Vec<Option<PendingStats>>, RunError> {
        if steps.len() != self.slots.len() {
            return Err(RunError::Internal(format!(
                "pack engine: {} slot inputs for a pack of {} runs",
                steps.len(),
                self.slots.len()
            )));
        }
        // Every input checked before any slot steps: a refused step leaves every slot as it was.
        for (i, (slot, input)) in self.slots.iter().zip(&steps).enumerate() {
            let Some(input) = input else { continue };
            if input.batch.prompt.is_some() != slot.spec.uses_prompt {
                return Err(RunError::Internal(format!(
                    "pack engine: slot {i}'s batch {} a prompt, but its run {}",
                    if input.batch.prompt.is_some() { "has" } else { "lacks" },
                    if slot.spec.uses_prompt { "uses one" } else { "uses none" }
                )));
            }
        }
        Ok(self
            .slots
            .iter_mut()
            .zip(steps)
            .map(|(slot, input)| {
                let input = input?;
                // The contract's dropout stream: the solo learner seeds the same.
                tch::manual_seed(derive_seed(slot.spec.seed, STREAM_DROPOUT, input.step) as i64);
                let (batch, loss_on) = (&input.batch, slot.spec.loss_on);
                Some(train_step_with(
                    &slot.model,
                    &mut slot.opt,
                    batch,
                    loss_on,
                    input.step,
                    Dropout::Draw,
                ))
            })
            .collect())
    }

    fn export(&self, slot: usize) -> Result<SlotState, RunError> {
        let s = self.slot(slot)?;
        Ok(SlotState::copy_of(&s.vs, &s.opt))
    }

    fn import(&mut self, slot: usize, state: SlotState) -> Result<(), RunError> {
        self.slot(slot)?;
        let s = &mut self.slots[slot];
        state
            .copy_into(&s.vs, &mut s.opt)
            .map_err(|e| RunError::Internal(format!("pack engine: slot {slot}: {e}")))
    }
}
