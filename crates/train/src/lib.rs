//! Training Prompt-DT.
//!
//! - [`optim`]: AdamW, linear warm-up and global gradient-norm clipping, written to reproduce
//!   PyTorch's `torch.optim.AdamW` (single-tensor CPU path), `LambdaLR` and `clip_grad_norm_`
//!   bit for bit, with a state that can be saved and restored for resumable runs.
//! - [`step`]: one gradient step on a sampled batch (the reference's `train_step_mix`).

// Errors carry the offending path, shape or tensor name, so they are large; they are returned
// on the cold path only (a failed run), where their size costs nothing.
#![allow(clippy::result_large_err)]

pub mod config;
mod macaw;
pub mod optim;
pub mod run;
pub mod smoke;
pub mod step;
