//! The interface between a pack's runs and the engine that steps them together.
//!
//! Contract (every engine):
//! - A slot's results depend on that slot's inputs alone: never on which other slots are active in
//!   a step, nor on their data (so a pack resumed after a kill, with its runs at different
//!   iterations, continues each run exactly as an uninterrupted pack would).
//! - Dropout: a slot's masks for its gradient step `s` come from libtorch's generator seeded with
//!   `derive_seed(spec.seed, STREAM_DROPOUT, s)` and drawn in the solo model's order and shapes, as
//!   the solo learner draws them; so a run's dropout masks are the same packed or solo (on the CPU).
//! - A slot given `None` in a step is left exactly as it was (weights, moments, step counts).
//! - Parameters a slot's run never uses (the prompt layers of a no-prompt run; the heads no loss
//!   reads) get no update and no step count for that slot, as PyTorch skips a `None` gradient.

use pdt_train::run::RunError;
// A slot's state is a solo run's, so the optimiser owns its type (the solo learner hands it over).
use pdt_train::optim::SlotState;

use pdt_model::PromptDtConfig;
use pdt_rundir::config::{AdamWConfig, LastBlockChoice, LossOn};
use pdt_train::step::{DeviceBatch, PendingStats};

/// What an engine knows about one run of the pack, fixed for the pack's life.
#[derive(Debug, Clone)]
pub struct SlotSpec {
    /// The run's model shape (width, depth, heads and max lengths must agree across the pack;
    /// prompt lengths may differ).
    pub model: PromptDtConfig,
    /// The run's prompt is prepended (Prompt-DT, Prompt-MT-BC); `false` for MT-ORL and the MT-BC
    /// variants (no prompt tokens).
    pub uses_prompt: bool,
    pub loss_on: LossOn,
    pub optim: AdamWConfig,
    /// The run's `train.last_block` (the runs of a batched pack agree on what it resolves to).
    pub last_block: LastBlockChoice,
    /// The run seed (its dropout stream; see the module contract).
    pub seed: u64,
}

/// One run's input to a pack step.
#[derive(Debug)]
pub struct SlotStep {
    /// The run's gradient step index (0-based): its learning rate and dropout stream.
    pub step: u64,
    /// The run's sampled batch on the pack's device (its prompt `None` when the run uses none).
    pub batch: DeviceBatch,
}

/// Steps the runs of a pack together.
pub trait PackEngine {
    /// Number of slots (runs) in the pack.
    fn slots(&self) -> usize;
    /// One gradient step for every slot given `Some` (the result at the same position); slots
    /// given `None` are untouched and get `None`. `steps.len() == self.slots()`. The statistics
    /// may be left on the device, for the run to read when it needs them.
    fn step(&mut self, steps: Vec<Option<SlotStep>>)
        -> Result<Vec<Option<PendingStats>>, RunError>;
    /// The slot's current weights and optimiser state, as a solo run holds them.
    fn export(&self, slot: usize) -> Result<SlotState, RunError>;
    /// Sets the slot's weights and optimiser state (a fresh run's initial weights with empty
    /// moments, or a resumed run's checkpoint).
    fn import(&mut self, slot: usize, state: SlotState) -> Result<(), RunError>;
}
