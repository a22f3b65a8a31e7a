//! The exact engine: each slot an ordinary solo model (`PromptDt` and `crate::optim::Optimizer`),
//! stepped one after another with the solo step (`crate::step::train_step`). A run trained through
//! it is the same run trained alone, bit for bit; it is the fallback for whatever the batched
//! engine cannot pack, and the reference the batched engine is tested against.

use super::engine::{PackEngine, SlotSpec, SlotState, SlotStep};
use crate::error::RunError;
use crate::optim::Optimizer;
use crate::step::{train_step, StepStats};
use crate::streams::STREAM_DROPOUT;
use pdt_base::seed::derive_seed;
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

/// N solo models stepped one after another.
pub struct SoloEngine {
    slots: Vec<Slot>,
}

impl SoloEngine {
    /// One slot per spec on `device`. Building a model draws its initial weights from libtorch's
    /// generator: call it with `crate::streams::torch_rng_lock` held. The weights drawn here are
    /// placeholders: each run imports its own (its seed's initialisation or its checkpoint)
    /// before its first step.
    pub fn new(specs: Vec<SlotSpec>, device: Device) -> Self {
        let slots = specs
            .into_iter()
            .map(|spec| {
                let vs = VarStore::new(device);
                let model = PromptDt::new(&vs.root(), &spec.model);
                let opt = Optimizer::new(&vs, &spec.model.parameter_names(), spec.optim.clone());
                Slot { spec, vs, model, opt }
            })
            .collect();
        Self { slots }
    }

    fn slot(&self, slot: usize) -> Result<&Slot, RunError> {
        self.slots.get(slot).ok_or_else(|| no_slot(slot, self.slots.len()))
    }
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
        let mut out = Vec::with_capacity(steps.len());
        for (i, (slot, input)) in self.slots.iter_mut().zip(steps).enumerate() {
            let Some(input) = input else {
                out.push(None);
                continue;
            };
            if input.batch.prompt.is_some() != slot.spec.uses_prompt {
                return Err(RunError::Invalid(format!(
                    "pack engine: slot {i}'s batch {} a prompt, but its run {}",
                    if input.batch.prompt.is_some() { "has" } else { "lacks" },
                    if slot.spec.uses_prompt { "uses one" } else { "uses none" }
                )));
            }
            // The contract's dropout stream: the solo learner seeds the same before its step.
            tch::manual_seed(derive_seed(slot.spec.seed, STREAM_DROPOUT, input.step) as i64);
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
