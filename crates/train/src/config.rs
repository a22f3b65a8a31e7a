//! The training configuration: one TOML file, every section optional, defaults equal to the
//! reference code's values (`promptdt-reference.md` c.3, c.4). Per-environment constants (rtg scale,
//! target return, horizon, prompt length) come from the environment's preset unless set here.

use crate::optim::AdamWConfig;
use crate::step::LossOn;
use pdt_data::multitask::DataFormat;
use pdt_model::device::DeviceSpec;
use pdt_prompt::{NormalizationScope, PromptPosition, TrajectoryRanking};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// The methods of the paper's comparison.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Prompt-DT: prompt + returns-to-go.
    #[default]
    PromptDt,
    /// Prompt-MT-BC: prompt, history returns-to-go zeroed in training (`--no-rtg --no-r`).
    PromptMtBc,
    /// MT-ORL: returns-to-go, no prompt (`--no-prompt`).
    MtOrl,
    /// MT-BC-Finetune: no prompt, no returns-to-go; fine-tuned on each test task's demonstrations
    /// before evaluation (`--no-prompt --no-rtg --no-r --finetune`).
    MtBcFinetune,
}

impl Method {
    pub fn uses_prompt(self) -> bool {
        matches!(self, Method::PromptDt | Method::PromptMtBc)
    }

    pub fn zeroes_history_returns(self) -> bool {
        matches!(self, Method::PromptMtBc | Method::MtBcFinetune)
    }

    pub fn name(self) -> &'static str {
        match self {
            Method::PromptDt => "prompt-dt",
            Method::PromptMtBc => "prompt-mt-bc",
            Method::MtOrl => "mt-orl",
            Method::MtBcFinetune => "mt-bc-finetune",
        }
    }
}

/// How Prompt-MT-BC and MT-BC-Finetune are evaluated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MtBcEval {
    /// Reference code: history returns-to-go are the constant G*/scale, although training saw 0.
    #[default]
    Reference,
    /// The paper: return tokens carry no information, so they are 0 as in training.
    Paper,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunSection {
    pub method: Method,
    pub seed: u64,
    pub device: DeviceSpec,
    /// libtorch intra-op threads; 0 = all cores.
    pub threads: usize,
}

impl Default for RunSection {
    fn default() -> Self {
        Self { method: Method::PromptDt, seed: 0, device: DeviceSpec::Auto, threads: 0 }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EnvSection {
    /// Task family (`point_robot`, later `cheetah_dir`, `cheetah_vel`, `ant_dir`).
    pub name: String,
    /// Named train/test split of the family.
    pub split: String,
}

impl Default for EnvSection {
    fn default() -> Self {
        Self { name: "point_robot".into(), split: "default".into() }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DataSection {
    /// Directory with `{env}-{task}-{mode}.{safetensors,pkl}` files.
    pub dir: PathBuf,
    pub dataset_mode: String,
    pub prompt_mode: String,
    pub test_dataset_mode: String,
    pub test_prompt_mode: String,
    pub format: DataFormat,
    pub normalization: NormalizationScope,
}

impl Default for DataSection {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("data/point_robot"),
            dataset_mode: "expert".into(),
            prompt_mode: "expert".into(),
            test_dataset_mode: "expert".into(),
            test_prompt_mode: "expert".into(),
            format: DataFormat::Auto,
            normalization: NormalizationScope::TrainAndTest,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SamplerSection {
    pub k: usize,
    pub prompt_episodes: usize,
    /// Prompt segment length H; default: the environment's preset.
    pub prompt_length: Option<usize>,
    pub prompt_position: PromptPosition,
    /// Samples per training task per batch (reference code 16, paper 8).
    pub batch_size_per_task: usize,
    pub ranking: TrajectoryRanking,
    /// Return-to-go divisor; default: the environment's preset.
    pub rtg_scale: Option<f32>,
}

impl Default for SamplerSection {
    fn default() -> Self {
        Self {
            k: 20,
            prompt_episodes: 1,
            prompt_length: None,
            prompt_position: PromptPosition::Tail,
            batch_size_per_task: 16,
            ranking: TrajectoryRanking::ReferenceOffByOne,
            rtg_scale: None,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelSection {
    pub hidden_size: usize,
    pub n_layer: usize,
    pub n_head: usize,
    pub n_inner: usize,
    pub max_ep_len: usize,
    pub n_positions: usize,
    /// Residual and attention dropout (the reference's `--dropout`).
    pub dropout: f64,
    /// Dropout on the input embeddings (HF's `embd_pdrop`, not set by the reference's `--dropout`).
    pub embd_dropout: f64,
}

impl Default for ModelSection {
    fn default() -> Self {
        Self {
            hidden_size: 128,
            n_layer: 3,
            n_head: 1,
            n_inner: 512,
            max_ep_len: 1000,
            n_positions: 1024,
            dropout: 0.1,
            embd_dropout: 0.1,
        }
    }
}

impl ModelSection {
    pub fn to_model_config(&self, state_dim: usize, act_dim: usize) -> pdt_model::PromptDtConfig {
        pdt_model::PromptDtConfig {
            hidden_size: self.hidden_size,
            n_layer: self.n_layer,
            n_head: self.n_head,
            n_inner: self.n_inner,
            max_ep_len: self.max_ep_len,
            n_positions: self.n_positions,
            resid_pdrop: self.dropout,
            attn_pdrop: self.dropout,
            embd_pdrop: self.embd_dropout,
            ..pdt_model::PromptDtConfig::reference(state_dim, act_dim)
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainSection {
    /// Training iterations (reference 5000).
    pub iterations: u64,
    /// Gradient steps per iteration (reference 10).
    pub steps_per_iteration: u64,
    pub loss_on: LossOn,
    /// Evaluate the test tasks after iterations 1, 1 + n, 1 + 2n, ... and the last (reference 100).
    pub test_eval_interval: u64,
    /// Same for the training tasks (reference 500; 0 = never).
    pub train_eval_interval: u64,
    /// Checkpoint every n iterations and after the last (reference 500); these weights are kept.
    pub save_interval: u64,
    /// Also write a resume point every n iterations (0 = only the checkpoints above). Not in the
    /// reference: long runs on a machine that may stop lose at most n iterations. A resume point
    /// that is not a checkpoint is removed when the next one is written, so it costs one extra
    /// weights file; results do not depend on it (a resumed run is byte-identical).
    pub resume_interval: u64,
}

impl Default for TrainSection {
    fn default() -> Self {
        Self {
            iterations: 5000,
            steps_per_iteration: 10,
            loss_on: LossOn::History,
            test_eval_interval: 100,
            train_eval_interval: 500,
            save_interval: 500,
            resume_interval: 0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalSection {
    /// Episodes per task (reference code 50, paper 20).
    pub episodes: usize,
    /// Target return G*; default: the environment's preset.
    pub target_return: Option<f32>,
    pub mt_bc_returns: MtBcEval,
    /// Largest number of episodes in one forward pass (1 reproduces the reference's loop).
    pub max_batch: usize,
    /// Threads stepping environments during evaluation (results do not depend on it); 0 = all cores.
    pub env_threads: usize,
    /// MT-BC-Finetune: gradient steps on each test task (reference 10).
    pub finetune_steps: u64,
    /// MT-BC-Finetune: segments per fine-tuning batch (reference 256).
    pub finetune_batch: usize,
    pub finetune_lr: f64,
}

impl Default for EvalSection {
    fn default() -> Self {
        Self {
            episodes: 50,
            target_return: None,
            mt_bc_returns: MtBcEval::Reference,
            max_batch: 4096,
            env_threads: 0,
            finetune_steps: 10,
            finetune_batch: 256,
            finetune_lr: 1e-4,
        }
    }
}

/// A whole experiment.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    pub run: RunSection,
    pub env: EnvSection,
    pub data: DataSection,
    pub sampler: SamplerSection,
    pub model: ModelSection,
    pub optim: AdamWConfig,
    pub train: TrainSection,
    pub eval: EvalSection,
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("invalid configuration: {0}")]
    Invalid(String),
}

impl TrainConfig {
    /// Reads a TOML file; unknown keys are errors (a typo must not silently fall back to a default).
    pub fn from_file(path: &std::path::Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ConfigError::Io { path: path.into(), source })?;
        toml::from_str(&text)
            .map_err(|e| ConfigError::Parse { path: path.into(), message: e.to_string() })
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# could not serialise: {e}\n"))
    }

    /// Checks what can be checked without data.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |m: String| Err(ConfigError::Invalid(m));
        if self.train.iterations == 0 || self.train.steps_per_iteration == 0 {
            return bad("train.iterations and train.steps_per_iteration must be at least 1".into());
        }
        if self.train.test_eval_interval == 0 || self.train.save_interval == 0 {
            return bad(
                "train.test_eval_interval and train.save_interval must be at least 1".into()
            );
        }
        if self.eval.episodes == 0 || self.eval.max_batch == 0 {
            return bad("eval.episodes and eval.max_batch must be at least 1".into());
        }
        if !(self.optim.learning_rate > 0.0 && self.optim.learning_rate.is_finite()) {
            return bad(format!(
                "optim.learning_rate must be positive, got {}",
                self.optim.learning_rate
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_file_gives_the_reference_defaults_and_round_trips() {
        let c: TrainConfig = toml::from_str("").unwrap();
        assert_eq!(c.sampler.batch_size_per_task, 16);
        assert_eq!(c.sampler.k, 20);
        assert_eq!(c.optim.warmup_steps, 10_000);
        assert_eq!(c.optim.grad_clip_norm, 0.25);
        assert_eq!(c.train.iterations, 5000);
        assert_eq!(c.eval.episodes, 50);
        let back: TrainConfig = toml::from_str(&c.to_toml()).unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn unknown_keys_are_rejected_with_their_name() {
        let e = toml::from_str::<TrainConfig>("[train]\niteratons = 3\n").unwrap_err().to_string();
        assert!(e.contains("iteratons"), "{e}");
        let c: TrainConfig =
            toml::from_str("[run]\nmethod = \"mt-orl\"\n[sampler]\nprompt_position = \"random\"\n")
                .unwrap();
        assert_eq!(c.run.method, Method::MtOrl);
        assert!(!c.run.method.uses_prompt());
    }
}
