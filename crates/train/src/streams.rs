//! A run's randomness: independent streams derived from the run seed (SplitMix64 of seed, stream,
//! counter: `pdt_base::seed::derive_seed`), and the lock on libtorch's global generator.

/// Model initialisation (libtorch's generator, seeded once per learner).
pub const STREAM_INIT: u64 = 1;
/// Batch (and, for MACAW, task) sampling: one generator, its position saved in checkpoints.
pub(crate) const STREAM_BATCHES: u64 = 2;
/// Dropout (libtorch's generator, re-seeded per gradient step: `derive_seed(seed, 3, step)`).
pub const STREAM_DROPOUT: u64 = 3;
/// Evaluations of the test and of the training tasks, per iteration: owned by `pdt_policy`, whose
/// evaluation plans draw what the run's evaluations draw.
pub(crate) use pdt_policy::policy::{STREAM_EVAL_TEST, STREAM_EVAL_TRAIN};

/// libtorch's random generator (weight init, dropout) is global to the process: runs in one process
/// take turns, so that each run's draws depend on its seed alone.
static TORCH_RNG: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub fn torch_rng_lock() -> std::sync::MutexGuard<'static, ()> {
    TORCH_RNG.lock().unwrap_or_else(|e| e.into_inner())
}
