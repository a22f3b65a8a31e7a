//! What promptdt needs of libtorch beyond tch's bindings, apart from any model: the C++ functions
//! of `csrc/` (compiled by build.rs against the linked libtorch's headers) and the Rust around
//! them.
//!
//! - [`device`]: CPU/CUDA selection (loading libtorch's CUDA part at run time), cuBLAS's TF32
//!   switch, uploads through pinned memory.
//! - [`autocast`]: bf16 mixed precision (libtorch's autocast around a forward pass) and whether the
//!   hardware computes bf16 natively.
//! - [`bernoulli`]: `bernoulli_`'s bits on the CPU, drawn a block at a time (dropout's noise).
//! - [`profiler`]: libtorch's own profiler (Kineto) around a piece of work.
//! - [`host_memory`]: keeps the memory libtorch frees on the CPU for reuse (no page-fault churn).
//!
//! The model (`pdt-model`) and everything that trains, evaluates or measures use these; nothing
//! here knows a model, a run or an environment.

pub mod autocast;
pub mod bernoulli;
pub mod device;
mod ffi;
pub mod host_memory;
pub mod profiler;
