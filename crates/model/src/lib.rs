//! The Prompt-DT model (Xu et al. 2022) on tch, written to match the reference PyTorch code op for op.
//!
//! - [`config`]: [`PromptDtConfig`] with the reference's hyper-parameters.
//! - [`gpt2`]: the GPT-2 trunk without position embedding (the reference's `trajectory_gpt2.py`).
//! - [`prompt_dt`]: embeddings, token interleaving, prompt concatenation, heads, masked MSE loss.
//! - [`lora`]: LoRA adapters on the attention projections, held apart from the weights.
//! - [`checkpoint`]: weights as safetensors with the reference `state_dict` names, both ways.
//! - [`dropout`]: the trunk's dropout sites and masks (drawn in the forward or beforehand).
//! - [`tokens`]: the `(R, s, a)` token layout (the state tokens' rows).
//! - [`forward_file`]: `promptdt model forward` on inputs stored in safetensors.
//!
//! libtorch's plumbing (devices, uploads, the C++ shims, the profiler, the host allocator) is
//! `pdt-torch`'s.
//!
//! Parameter names equal the reference `state_dict` keys (`transformer.h.0.attn.c_attn.weight`, ...)
//! so a checkpoint moves between promptdt and PyTorch without renaming.

// Errors carry the offending path, shape or tensor name, so they are large; they are returned
// on the cold path only (a failed run), where their size costs nothing.
#![allow(clippy::result_large_err)]

pub mod checkpoint;
pub mod config;
pub mod dropout;
pub mod forward_file;
pub mod gpt2;
pub mod lora;
pub mod prompt_dt;
pub mod tokens;

pub use checkpoint::CheckpointError;
pub use config::PromptDtConfig;
pub use gpt2::{LastBlock, PrefixCache};
pub use lora::{LoraAdapters, LoraLayer, LoraPair, LoraShape};
pub use prompt_dt::{PromptDt, PromptTokens, Segments};
