//! Option types of the configuration that the crates acting on them re-export: the optimiser's
//! settings (`pdt_train::optim`), the loss's target (`pdt_train::step`) and the evaluator's inference
//! path (`pdt_eval`). They live here so that `config.toml` is read without libtorch.

use serde::{Deserialize, Serialize};

/// AdamW settings. Defaults are the reference's (`torch.optim.AdamW(lr=1e-4, weight_decay=1e-4)`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AdamWConfig {
    /// Peak learning rate, reached at the end of warm-up.
    pub learning_rate: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Decoupled weight decay, applied (as in the reference) to every parameter that has a
    /// gradient, LayerNorm weights, biases and embeddings included.
    pub weight_decay: f64,
    /// Linear warm-up length in steps: lr(n) = learning_rate * min((n + 1) / warmup_steps, 1).
    pub warmup_steps: u64,
    /// Global L2 gradient-norm clipping threshold.
    pub grad_clip_norm: f64,
    /// Whether clipping and AdamW run on one flat buffer (`pdt_train::optim::FlatAdamW`: a fixed
    /// handful of kernels per step) or loop over the parameter tensors (`AdamW`: PyTorch's
    /// single-tensor path, bit for bit on CPU). Left out of `config.toml` at its default, so files
    /// written before it existed and files written now at the default are the same.
    #[serde(skip_serializing_if = "FlatOptim::is_auto")]
    pub flat: FlatOptim,
}

/// `optim.flat`: which AdamW implementation a run steps with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FlatOptim {
    /// Flat on CUDA, where per-tensor kernel launches dominate a step; per-tensor on CPU, where
    /// the bitwise parity with PyTorch holds.
    #[default]
    Auto,
    /// Always the flat buffer (results within a tolerance of PyTorch's, not bit for bit).
    On,
    /// Always the per-tensor loops.
    Off,
}

impl FlatOptim {
    pub fn is_auto(&self) -> bool {
        *self == FlatOptim::Auto
    }

    /// Whether the flat optimiser is used on a device that is (`cuda = true`) or is not CUDA.
    pub fn use_flat(self, cuda: bool) -> bool {
        match self {
            FlatOptim::Auto => cuda,
            FlatOptim::On => true,
            FlatOptim::Off => false,
        }
    }
}

/// `train.last_block`: which positions the last transformer block of a training forward computes
/// (`pdt_model::LastBlock`; docs/implementation-details.md, C.9).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LastBlockChoice {
    /// A solo model: the state tokens only on CUDA, every token on the CPU (the bitwise parity
    /// with PyTorch). A batched pack: the state tokens only (no batched path is bitwise).
    #[default]
    Auto,
    /// Every token: the reference's ops.
    AllTokens,
    /// The state tokens only, the only outputs the action head reads: the same values in exact
    /// arithmetic for a third of the last block's rows (within a tolerance of `all_tokens`).
    StateTokens,
}

impl LastBlockChoice {
    pub fn is_auto(&self) -> bool {
        *self == LastBlockChoice::Auto
    }

    /// Whether the last block runs for the state tokens only: for a solo model on a device that is
    /// (`cuda = true`) or is not CUDA, or (`batched = true`) for a batched pack.
    pub fn state_tokens(self, cuda: bool, batched: bool) -> bool {
        match self {
            LastBlockChoice::Auto => cuda || batched,
            LastBlockChoice::AllTokens => false,
            LastBlockChoice::StateTokens => true,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            LastBlockChoice::Auto => "auto",
            LastBlockChoice::AllTokens => "all_tokens",
            LastBlockChoice::StateTokens => "state_tokens",
        }
    }
}

impl Default for AdamWConfig {
    fn default() -> Self {
        Self {
            learning_rate: 1e-4,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 1e-4,
            warmup_steps: 10_000,
            grad_clip_norm: 0.25,
            flat: FlatOptim::Auto,
        }
    }
}

impl AdamWConfig {
    /// The learning rate of gradient step `n` (0-based): PyTorch's `LambdaLR` with
    /// `lambda s: min((s + 1) / warmup_steps, 1)`, stepped once per gradient step.
    pub fn lr_at(&self, n: u64) -> f64 {
        let warm = self.warmup_steps.max(1) as f64;
        self.learning_rate * f64::min((n + 1) as f64 / warm, 1.0)
    }
}

/// Which predicted actions the loss supervises.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LossOn {
    /// Reference code (pitfall 3): only the K history steps.
    #[default]
    History,
    /// The paper (section 4.4): the prompt's steps too.
    PromptAndHistory,
}

/// How the policy computes an action at each step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Inference {
    /// `PromptDt::forward` with `Act`: the prompt's keys and values computed once per task and
    /// evaluation, the last layer for the last 8 positions only. Equal to `Full` within 1e-6 (a few f32 ulps:
    /// other kernel paths), not bit for bit. Not in the reference.
    #[default]
    Cached,
    /// The reference's `get_action`: the full forward of prompt and history at every step.
    Full,
}
