//! A run's random streams: independent generators derived from the run seed (SplitMix64 of seed,
//! stream, counter: `pdt_base::seed::derive_seed`). Numbered in one place because the trainer
//! (initialisation, batches, dropout, its evaluations) and an acting policy's evaluation plans
//! (which draw what the run's final evaluation draws) must agree on them, and two owners could
//! hand out one number twice.

/// Model initialisation (libtorch's generator, seeded once per learner).
pub const STREAM_INIT: u64 = 1;
/// Batch (and, for MACAW, task) sampling: one generator, its position saved in checkpoints.
pub const STREAM_BATCHES: u64 = 2;
/// Dropout (libtorch's generator, re-seeded per gradient step: `derive_seed(seed, 3, step)`).
pub const STREAM_DROPOUT: u64 = 3;
/// Evaluations of the test tasks, per iteration (a final evaluation's counter is
/// `u64::MAX - iteration`).
pub const STREAM_EVAL_TEST: u64 = 4;
/// Evaluations of the training tasks, per iteration.
pub const STREAM_EVAL_TRAIN: u64 = 5;
