//! Training Prompt-DT and the baselines of its comparison.
//!
//! - [`run`]: the public face of a run (train, evaluate, serve a trained run).
//! - `run_loop`: the one loop every method runs in (cadence, logs, checkpoints, resumption).
//! - [`methods`]: the [`Learner`](methods::Learner) trait, its implementations (the Prompt-DT
//!   family, MACAW) and the registry mapping `run.method` to one; and
//!   [`Steppable`](methods::Steppable), the learner a pack (`pdt-pack`, above this crate) takes
//!   the gradient steps of.
//! - [`setup`]: the configuration checked against its environment and data, the data loaded
//!   (`pdt_run::RunData`).
//! - `run_dir`: the trainer's bookkeeping of the run directory (logs cut back on resume, checkpoint
//!   commits, clean-up after a kill) over `pdt_rundir`'s typed files.
//! - `evaluate`: the final evaluation of a run (`eval_final.json`).
//! - `offline`: the final evaluation of a run with no environment (`eval_offline.json`: the
//!   action error on the tasks' data).
//! - [`streams`]: the lock on libtorch's one random generator that runs sharing a process take
//!   turns at (the run seed's streams are numbered in `pdt_run::streams`).
//! - [`optim`]: AdamW, linear warm-up and global gradient-norm clipping, written to reproduce
//!   PyTorch's `torch.optim.AdamW` (single-tensor CPU path), `LambdaLR` and `clip_grad_norm_`
//!   bit for bit, with a state that can be saved and restored for resumable runs; `FlatAdamW`,
//!   the same maths over one flat buffer (a fixed handful of kernels per step, for CUDA), and
//!   `Optimizer`, either of them as `optim.flat` chooses.
//! - [`step`]: one gradient step on a sampled batch (the reference's `train_step_mix`).

// Errors carry the offending path, shape or tensor name, so they are large; they are returned
// on the cold path only (a failed run), where their size costs nothing.
#![allow(clippy::result_large_err)]

mod error;
mod evaluate;
pub mod methods;
mod offline;
pub mod optim;
pub mod run;
mod run_dir;
mod run_loop;
pub mod setup;
pub mod smoke;
pub mod step;
pub mod streams;
