//! `[eval.adapt]`: an evaluation-time adaptation to each test task from its few demonstrations,
//! the backbone frozen, or all of it fine-tuned for the task (`docs/prompt-control.md`). The algorithms are
//! `pdt_eval::testtime::adapt`'s; this is their configuration, read without libtorch.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// Which adaptation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AdaptKind {
    /// None: the model as trained (the default).
    #[default]
    None,
    /// Soft prompt tuning: the embedded prompt tokens learned by gradient steps.
    SoftPrompt,
    /// Prompt-Tuning DT (Hu et al. 2023): ranking-based zeroth-order update of the prompt.
    Ptdt,
    /// LoRA adapters on the attention projections.
    Lora,
    /// Full fine-tuning: every weight of the model, with the data, optimiser, steps and batch of
    /// the others (Prompt-Tuning DT's full-fine-tuning baseline), the weights restored after the
    /// task's episodes.
    Full,
}

impl AdaptKind {
    pub const ALL: [AdaptKind; 5] =
        [AdaptKind::None, AdaptKind::SoftPrompt, AdaptKind::Ptdt, AdaptKind::Lora, AdaptKind::Full];

    pub fn name(self) -> &'static str {
        match self {
            AdaptKind::None => "none",
            AdaptKind::SoftPrompt => "soft-prompt",
            AdaptKind::Ptdt => "ptdt",
            AdaptKind::Lora => "lora",
            AdaptKind::Full => "full",
        }
    }
}

impl fmt::Display for AdaptKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// An unknown adaptation name or a setting out of range; the message names the value.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct AdaptError(pub String);

impl FromStr for AdaptKind {
    type Err = AdaptError;
    fn from_str(s: &str) -> Result<Self, AdaptError> {
        Self::ALL.into_iter().find(|k| k.name() == s).ok_or_else(|| {
            let known: Vec<&str> = Self::ALL.iter().map(|k| k.name()).collect();
            AdaptError(format!("unknown adaptation `{s}` (known: {})", known.join(", ")))
        })
    }
}

/// What the Prompt-Tuning DT update ranks its candidates by (the paper has an offline and an
/// online variant; which one is a choice here).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PtdtScore {
    /// The demonstrations' action loss (lower is better): offline, no environment steps.
    #[default]
    ActionLoss,
    /// The mean return of `score_episodes` episodes per candidate in the task's environment
    /// (higher is better), on reset seeds apart from the evaluation's.
    Return,
}

/// `[eval.adapt.ptdt]`: the zeroth-order update's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PtdtConfig {
    /// Candidates (Gaussian perturbations of the prompt) per iteration (at least 2).
    pub candidates: usize,
    /// Standard deviation of the perturbations, in the prompt's (normalised) input units.
    pub sigma: f64,
    /// Step along the ranking direction, in the same units (the direction is a mean of
    /// differences of unit Gaussian perturbations).
    pub step: f64,
    pub score: PtdtScore,
    /// `score = "return"`: episodes per candidate.
    pub score_episodes: usize,
}

impl Default for PtdtConfig {
    fn default() -> Self {
        Self {
            candidates: 8,
            sigma: 0.05,
            step: 0.05,
            score: PtdtScore::ActionLoss,
            score_episodes: 1,
        }
    }
}

/// `[eval.adapt.lora]`: the adapters' shape.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoraConfig {
    /// Rank r.
    pub rank: usize,
    /// The delta is scaled by alpha / r.
    pub alpha: f64,
    /// Also adapt `attn.c_proj` (`attn.c_attn` always is).
    pub c_proj: bool,
    /// Standard deviation of A's initial values (B starts at zero).
    pub init_std: f64,
}

impl Default for LoraConfig {
    fn default() -> Self {
        Self { rank: 4, alpha: 8.0, c_proj: false, init_std: 0.02 }
    }
}

/// `[eval.adapt]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AdaptConfig {
    pub kind: AdaptKind,
    /// Iterations per test task (gradient steps; PTDT: ranking updates).
    pub steps: usize,
    /// Demonstration segments (K steps each) per iteration.
    pub batch: usize,
    /// Adam's learning rate (soft prompt, LoRA, full fine-tuning; PTDT has `ptdt.step`).
    pub lr: f64,
    pub ptdt: PtdtConfig,
    pub lora: LoraConfig,
}

impl Default for AdaptConfig {
    fn default() -> Self {
        Self {
            kind: AdaptKind::None,
            steps: 20,
            batch: 16,
            lr: 1e-3,
            ptdt: PtdtConfig::default(),
            lora: LoraConfig::default(),
        }
    }
}

impl AdaptConfig {
    /// Whether no adaptation is asked for (then the section is not written).
    pub fn is_none(&self) -> bool {
        self.kind == AdaptKind::None
    }

    /// Refuses settings out of range, naming the setting and its value.
    pub fn validate(&self) -> Result<(), AdaptError> {
        let bad = |name: &str, v: String, want: &str| {
            Err(AdaptError(format!("eval.adapt.{name} = {v}: must be {want}")))
        };
        if self.steps == 0 || self.steps > 1_000_000 {
            return bad("steps", self.steps.to_string(), "in 1..=1000000");
        }
        if self.batch == 0 || self.batch > 100_000 {
            return bad("batch", self.batch.to_string(), "in 1..=100000");
        }
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr <= 10.0) {
            return bad("lr", self.lr.to_string(), "in (0, 10]");
        }
        let p = &self.ptdt;
        if p.candidates < 2 || p.candidates > 10_000 {
            return bad("ptdt.candidates", p.candidates.to_string(), "in 2..=10000");
        }
        if !(p.sigma.is_finite() && p.sigma > 0.0) {
            return bad("ptdt.sigma", p.sigma.to_string(), "finite and > 0");
        }
        if !(p.step.is_finite() && p.step > 0.0) {
            return bad("ptdt.step", p.step.to_string(), "finite and > 0");
        }
        if p.score_episodes == 0 || p.score_episodes > 10_000 {
            return bad("ptdt.score_episodes", p.score_episodes.to_string(), "in 1..=10000");
        }
        let l = &self.lora;
        if l.rank == 0 || l.rank > 4096 {
            return bad("lora.rank", l.rank.to_string(), "in 1..=4096");
        }
        if !(l.alpha.is_finite() && l.alpha > 0.0) {
            return bad("lora.alpha", l.alpha.to_string(), "finite and > 0");
        }
        if !(l.init_std.is_finite() && l.init_std > 0.0) {
            return bad("lora.init_std", l.init_std.to_string(), "finite and > 0");
        }
        Ok(())
    }
}

/// What an adaptation did to one test task (a row of `adapt_log` in `eval_adapt_<kind>.json`):
/// the demonstrations' action loss before and after (on one probe batch drawn before it
/// started), its budget and wall time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdaptLog {
    pub task: String,
    pub loss_before: f64,
    pub loss_after: f64,
    pub steps: usize,
    /// Values adapted (prompt tokens, prompt inputs, adapter weights or, fine-tuned in full, the
    /// model's weights).
    pub trainable: usize,
    /// Wall time of the adaptation (not of the episodes), seconds.
    pub seconds: f64,
}
