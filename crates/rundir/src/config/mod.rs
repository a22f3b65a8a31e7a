//! The training configuration: one TOML file, every section optional, defaults equal to the
//! reference code's values (`promptdt-reference.md` c.3, c.4). Per-environment constants (rtg scale,
//! target return, horizon, prompt length) come from the environment's preset unless set here.

pub mod adapt;
pub mod macaw;
mod method;
mod options;
mod overrides;
mod testtime;

pub use adapt::{AdaptConfig, AdaptError, AdaptKind, AdaptLog, LoraConfig, PtdtConfig, PtdtScore};
pub use method::Method;
pub use options::{AdamWConfig, FlatOptim, Inference, LastBlockChoice, LossOn};
pub use overrides::{Overrides, UnknownMethod};
use pdt_base::device::{DeviceSpec, Matmul};
use pdt_base::num::compact;
use pdt_data::multitask::DataFormat;
use pdt_prompt::{NormalizationScope, PromptPosition, PromptStrategy, TrajectoryRanking};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
pub use testtime::{Adaptation, TestTime};

/// The loss column of Prompt-DT-style runs written before `run.json` recorded `loss_metric`.
pub const LEGACY_LOSS_METRIC: &str = "train/action_loss";
/// The loss column of MACAW runs written before `run.json` recorded `loss_metric`.
pub const LEGACY_MACAW_LOSS_METRIC: &str = "train/policy_outer_loss";

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

/// What MT-BC-Finetune fine-tunes on, per test task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FinetuneData {
    /// The reference's `get_batch_finetune`: tail segments of the task's main dataset D_i.
    #[default]
    Dataset,
    /// The task's demonstrations P_i (its prompt set), K-step segments from uniformly drawn
    /// starts: the data the evaluation-time adaptations have (`[eval.adapt]`), so a fine-tuning
    /// at their budget is matched to them in data and steps.
    Prompts,
}

impl FinetuneData {
    pub fn is_dataset(&self) -> bool {
        *self == Self::Dataset
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunSection {
    pub method: Method,
    pub seed: u64,
    pub device: DeviceSpec,
    /// libtorch intra-op threads; 0 = all cores.
    pub threads: usize,
    /// The model's matrix products: `fp32` (default), `tf32` on a CUDA device (the reference's
    /// torch 1.10 default on Ampere and later GPUs) or `bf16` mixed precision (autocast; where the
    /// hardware has native bf16, or with `PROMPTDT_BF16_EMULATED=1`) ([`Matmul`]). Training
    /// refuses `tf32` on the CPU and `bf16` without native bf16; evaluating and serving there
    /// compute fp32. Written only when not the default.
    #[serde(skip_serializing_if = "Matmul::is_default")]
    pub matmul: Matmul,
}

impl Default for RunSection {
    fn default() -> Self {
        Self {
            method: Method::PromptDt,
            seed: 0,
            device: DeviceSpec::Auto,
            threads: 0,
            matmul: Matmul::Fp32,
        }
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
    /// Which positions the last transformer block computes in training (`auto`: the state tokens
    /// only on CUDA and in batched packs, every token in a solo CPU run). Left out of
    /// `config.toml` at its default.
    #[serde(skip_serializing_if = "LastBlockChoice::is_auto")]
    pub last_block: LastBlockChoice,
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
            last_block: LastBlockChoice::Auto,
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
    /// Threads stepping environments during evaluation (results do not depend on it); 0 = all cores
    /// (in a pack of N runs, each run's share: cores / N, rounded up).
    pub env_threads: usize,
    /// MT-BC-Finetune: gradient steps on each test task (reference 10).
    pub finetune_steps: u64,
    /// MT-BC-Finetune: segments per fine-tuning batch (reference 256).
    pub finetune_batch: usize,
    pub finetune_lr: f64,
    /// MT-BC-Finetune: fine-tune on the task's main dataset (`dataset`, the reference) or on its
    /// demonstrations (`prompts`). Written only when not the reference's, so the configuration
    /// files of runs that never set it are what they were.
    #[serde(skip_serializing_if = "FinetuneData::is_dataset")]
    pub finetune_data: FinetuneData,
    /// `cached` (default): the prompt's keys and values once per task and evaluation, the last
    /// layer for the last 8 positions only; `full`: the reference's full forward at every step.
    /// Equal within 1e-6, not bit for bit (`crates/model/tests/it/act.rs`).
    pub inference: Inference,
    /// `[eval.prompt]`: the test-time prompt strategy and length (`docs/prompt-control.md`).
    /// Written only when it differs from the default (`reference`, the training length), so the
    /// configuration files of runs that never set it are what they were.
    #[serde(skip_serializing_if = "PromptStrategy::is_default")]
    pub prompt: PromptStrategy,
    /// `[eval.adapt]`: an adaptation to each test task from its demonstrations, the backbone
    /// frozen (`docs/prompt-control.md`). Written only when one is set.
    #[serde(skip_serializing_if = "AdaptConfig::is_none")]
    pub adapt: AdaptConfig,
    /// History segments per task of an offline evaluation (a run with no environment: the
    /// prompted model's action error on the held-out tasks' data, `crate::offline`). Written
    /// only when not the default, so the configuration files of runs that never set it are what
    /// they were.
    #[serde(skip_serializing_if = "is_default_offline_segments")]
    pub offline_segments: usize,
}

/// `eval.offline_segments`'s default: 256 segments of K steps per task, a few thousand action
/// errors per task (its sampling noise well below a trained model's differences between tasks).
pub const DEFAULT_OFFLINE_SEGMENTS: usize = 256;

fn is_default_offline_segments(n: &usize) -> bool {
    *n == DEFAULT_OFFLINE_SEGMENTS
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
            finetune_data: FinetuneData::Dataset,
            inference: Inference::Cached,
            prompt: PromptStrategy::default(),
            adapt: AdaptConfig::default(),
            offline_segments: DEFAULT_OFFLINE_SEGMENTS,
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
    /// MACAW's hyper-parameters (used when `run.method = "macaw"`; default: the official
    /// `standard.json`). Written to `config.toml` for MACAW runs only ([`TrainConfig::to_toml`]);
    /// the files of other runs written before that have it, and still load.
    pub macaw: macaw::MacawConfig,
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
        let text = pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES)
            .map_err(|source| ConfigError::Io { path: path.into(), source })?;
        toml::from_str(&text)
            .map_err(|e| ConfigError::Parse { path: path.into(), message: e.to_string() })
    }

    /// The configuration as TOML. Fails rather than writing something that would not read back
    /// (TOML integers are signed 64-bit: a seed of 2^63 or more has no TOML form).
    ///
    /// Each method's configuration carries only its own sections: `[macaw]` is left out unless
    /// `run.method` is `macaw`.
    pub fn to_toml(&self) -> Result<String, ConfigError> {
        toml::to_string_pretty(&self.to_toml_value()?)
            .map_err(|e| ConfigError::Invalid(format!("cannot be written as TOML: {e}")))
    }

    /// The configuration as [`TrainConfig::to_toml`] writes it, as a TOML table (to compare two
    /// configurations as their files would).
    pub fn to_toml_value(&self) -> Result<toml::Value, ConfigError> {
        let mut v = toml::Value::try_from(self)
            .map_err(|e| ConfigError::Invalid(format!("cannot be written as TOML: {e}")))?;
        // Only the run's own method section is written.
        if let toml::Value::Table(t) = &mut v {
            let others = Method::ALL.into_iter().filter(|m| *m != self.run.method);
            for section in others.filter_map(Method::section) {
                t.remove(section);
            }
        }
        Ok(v)
    }

    /// Checks every setting that can be checked without data; the message names the setting and
    /// the allowed range. Ranges are wide (a user may try unusual values) but exclude what cannot
    /// train: a wrong sign, NaN, a size that could not be allocated.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let mut v = Checks::default();
        v.at_most("run.seed", self.run.seed, TOML_INT, "TOML integers are signed 64-bit");
        v.at_most("run.threads", self.run.threads as u64, 1024, "0 = all cores");
        let t = &self.train;
        v.range("train.iterations", t.iterations, 1, 100_000_000);
        v.range("train.steps_per_iteration", t.steps_per_iteration, 1, 100_000_000);
        v.range("train.test_eval_interval", t.test_eval_interval, 1, TOML_INT);
        v.at_most("train.train_eval_interval", t.train_eval_interval, TOML_INT, "0 = never");
        v.range("train.save_interval", t.save_interval, 1, TOML_INT);
        v.at_most("train.resume_interval", t.resume_interval, TOML_INT, "0 = only checkpoints");
        // The transformer's settings (model, optimiser, prompt sampling) are Prompt-DT's and its
        // variants'; MACAW reads its own section instead, so neither checks the other's.
        if self.run.method.is_transformer() {
            self.validate_transformer(&mut v);
        }
        let s = &self.sampler;
        if let Some(x) = s.rtg_scale {
            v.real("sampler.rtg_scale", f64::from(x), |x| x > 0.0 && x.is_finite(), "> 0");
        }
        // The modes become part of file names (`{env}-{task}-{mode}.{ext}`): a path there would
        // read files from elsewhere, an empty one a file no writer makes.
        let d = &self.data;
        for (name, mode) in [
            ("data.dataset_mode", &d.dataset_mode),
            ("data.prompt_mode", &d.prompt_mode),
            ("data.test_dataset_mode", &d.test_dataset_mode),
            ("data.test_prompt_mode", &d.test_prompt_mode),
        ] {
            if !is_plain_mode(mode) {
                v.fail(format!(
                    "{name} = {mode:?} must be a plain name (letters, digits, '-', '_' or '.', not \
                     starting with '.'): it becomes part of the data file names"
                ));
            }
        }
        let e = &self.eval;
        v.range("eval.episodes", e.episodes as u64, 1, 10_000);
        v.range("eval.max_batch", e.max_batch as u64, 1, 1_000_000);
        v.at_most("eval.env_threads", e.env_threads as u64, 1024, "0 = all cores");
        if let Some(x) = e.target_return {
            v.real("eval.target_return", f64::from(x), f64::is_finite, "finite");
        }
        v.range("eval.finetune_batch", e.finetune_batch as u64, 1, 1_000_000);
        v.range("eval.offline_segments", e.offline_segments as u64, 1, 1_000_000);
        v.at_most("eval.finetune_steps", e.finetune_steps, 100_000_000, "");
        v.real("eval.finetune_lr", e.finetune_lr, |x| x > 0.0 && x <= 1.0, "in (0, 1]");
        if let Err(err) = e.prompt.validate() {
            v.fail(format!("eval.prompt: {err}"));
        }
        if !e.prompt.is_default() && !self.run.method.uses_prompt() {
            v.fail(format!(
                "eval.prompt: {} takes no prompt; a prompt strategy applies to {} runs",
                self.run.method.name(),
                Method::names_where(Method::uses_prompt)
            ));
        }
        if let Err(err) = e.adapt.validate() {
            v.fail(err.to_string());
        }
        if !e.adapt.is_none() && !self.run.method.uses_prompt() {
            v.fail(format!(
                "eval.adapt.kind = {}: {} takes no prompt; the adaptations apply to {} runs",
                e.adapt.kind,
                self.run.method.name(),
                Method::names_where(Method::uses_prompt)
            ));
        }
        // Each method's own section is checked for its runs only (the others' are not written).
        match self.run.method {
            Method::Macaw => {
                if let Err(e) = self.macaw.validate() {
                    v.fail(e.to_string());
                }
            }
            Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune => {}
        }
        v.finish()
    }

    /// The checks of the settings only Prompt-DT and its variants read: `[model]`, `[optim]` and
    /// `[sampler]`'s batch and prompt settings.
    fn validate_transformer(&self, v: &mut Checks) {
        let o = &self.optim;
        v.real("optim.learning_rate", o.learning_rate, |x| x > 0.0 && x <= 1.0, "in (0, 1]");
        v.real("optim.beta1", o.beta1, |x| (0.0..1.0).contains(&x), "in [0, 1)");
        v.real("optim.beta2", o.beta2, |x| (0.0..1.0).contains(&x), "in [0, 1)");
        v.real("optim.eps", o.eps, |x| x > 0.0 && x <= 1.0, "in (0, 1]");
        v.real("optim.weight_decay", o.weight_decay, |x| (0.0..=1.0).contains(&x), "in [0, 1]");
        v.real("optim.grad_clip_norm", o.grad_clip_norm, |x| x > 0.0 && x.is_finite(), "> 0");
        v.at_most("optim.warmup_steps", o.warmup_steps, TOML_INT, "");
        let m = &self.model;
        v.range("model.hidden_size", m.hidden_size as u64, 1, 16_384);
        v.range("model.n_layer", m.n_layer as u64, 1, 256);
        v.range("model.n_head", m.n_head as u64, 1, 1024);
        if m.n_head > 0 && !m.hidden_size.is_multiple_of(m.n_head) {
            v.fail(format!(
                "model.n_head = {} must divide model.hidden_size = {}",
                m.n_head, m.hidden_size
            ));
        }
        v.range("model.n_inner", m.n_inner as u64, 1, 65_536);
        v.range("model.max_ep_len", m.max_ep_len as u64, 1, 1_000_000);
        v.range("model.n_positions", m.n_positions as u64, 1, 1_000_000);
        v.real("model.dropout", m.dropout, |x| (0.0..1.0).contains(&x), "in [0, 1)");
        v.real("model.embd_dropout", m.embd_dropout, |x| (0.0..1.0).contains(&x), "in [0, 1)");
        // Parameters (f32, plus two Adam moments): refuse what could not be allocated.
        let (h, l, i) = (m.hidden_size as f64, m.n_layer as f64, m.n_inner as f64);
        let params = l * (4.0 * h * h + 2.0 * h * i) + (m.max_ep_len + m.n_positions) as f64 * h;
        if params > 2e9 {
            v.fail(format!(
                "the model would have about {:.1e} parameters ({:.0} GB with its Adam moments); \
                 reduce model.hidden_size, model.n_layer or model.n_inner",
                params,
                params * 12.0 / 1e9
            ));
        }
        let s = &self.sampler;
        v.range("sampler.k", s.k as u64, 1, 100_000);
        v.range("sampler.batch_size_per_task", s.batch_size_per_task as u64, 1, 1_000_000);
        v.at_most("sampler.prompt_episodes", s.prompt_episodes as u64, 1000, "");
        if let Some(h) = s.prompt_length {
            v.range("sampler.prompt_length", h as u64, 1, 100_000);
        }
    }
}

/// A data mode usable in a file name: non-empty, letters, digits, `-`, `_` and `.`, not starting
/// with `.` (no path separators, no `..`, no hidden files).
fn is_plain_mode(mode: &str) -> bool {
    !mode.is_empty()
        && !mode.starts_with('.')
        && mode.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

/// The largest return-to-go token (a return divided by the rtg scale) accepted, in magnitude: the
/// target return's and the data's. The training data's tokens are of order 1 to 10; at 1e6 the
/// timestep embedding and bias added to the return embedding are already near f32 rounding, and
/// near 1e19 the squares of the embedding layer norm overflow f32 and every action is NaN.
pub const MAX_RETURN_TOKEN: f64 = 1e6;

/// The largest state mean (in magnitude) and state standard deviation accepted in a run's state
/// statistics. The families' observations are of order 1 to 100; a dimension whose std exceeds
/// 1e6 comes from corrupt data, and normalising by it maps every ordinary state to about 0.
pub const MAX_STATE_STAT: f64 = 1e6;

/// `|x| <= bound`, false for NaN: the test of [`MAX_RETURN_TOKEN`] and [`MAX_STATE_STAT`].
pub fn within(x: f64, bound: f64) -> bool {
    x.abs() <= bound
}

/// The largest TOML integer (TOML integers are signed 64-bit).
const TOML_INT: u64 = i64::MAX as u64;

/// Collects every failed check, so one run of `validate` names all bad settings at once.
#[derive(Default)]
struct Checks(Vec<String>);

impl Checks {
    fn fail(&mut self, m: String) {
        self.0.push(m);
    }
    fn range(&mut self, name: &str, x: u64, lo: u64, hi: u64) {
        if x < lo || x > hi {
            self.fail(format!("{name} must be between {lo} and {hi}, got {x}"));
        }
    }
    fn at_most(&mut self, name: &str, x: u64, hi: u64, note: &str) {
        if x > hi {
            let note = if note.is_empty() { String::new() } else { format!(" ({note})") };
            self.fail(format!("{name} must be at most {hi}{note}, got {x}"));
        }
    }
    fn real(&mut self, name: &str, x: f64, ok: impl Fn(f64) -> bool, what: &str) {
        if !ok(x) {
            self.fail(format!("{name} must be {what}, got {}", compact(x)));
        }
    }
    fn finish(self) -> Result<(), ConfigError> {
        if self.0.is_empty() {
            Ok(())
        } else {
            Err(ConfigError::Invalid(self.0.join("; ")))
        }
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
        let back: TrainConfig = toml::from_str(&c.to_toml().unwrap()).unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn run_matmul_defaults_to_fp32_is_written_only_when_set_and_is_valid_on_any_device() {
        let c: TrainConfig = toml::from_str("[run]\nseed = 1\n").unwrap();
        assert_eq!(c.run.matmul, Matmul::Fp32);
        assert!(!c.to_toml().unwrap().contains("matmul"), "files at the default stay as they were");
        let t: TrainConfig =
            toml::from_str("[run]\ndevice = \"cuda\"\nmatmul = \"tf32\"\n").unwrap();
        assert_eq!(t.run.matmul, Matmul::Tf32);
        assert!(t.to_toml().unwrap().contains("matmul = \"tf32\""));
        t.validate().unwrap();
        // A TF32 run's configuration stays valid on the CPU, where its checkpoints are evaluated
        // and served in fp32; training refuses it there (`pdt_torch::device::set_matmul`).
        let cpu: TrainConfig =
            toml::from_str("[run]\ndevice = \"cpu\"\nmatmul = \"tf32\"\n").unwrap();
        cpu.validate().unwrap();
        // bf16 (mixed precision) is a precision of its own; fp16 is none.
        let bf16: TrainConfig = toml::from_str("[run]\nmatmul = \"bf16\"\n").unwrap();
        assert_eq!(bf16.run.matmul, Matmul::Bf16);
        assert!(bf16.to_toml().unwrap().contains("matmul = \"bf16\""), "recorded in config.toml");
        assert!(toml::from_str::<TrainConfig>("[run]\nmatmul = \"fp16\"\n").is_err());
        for m in [Matmul::Fp32, Matmul::Tf32, Matmul::Bf16] {
            assert_eq!(m.as_str().parse::<Matmul>(), Ok(m));
        }
    }

    #[test]
    fn train_last_block_defaults_to_auto_and_is_written_only_when_set() {
        let c: TrainConfig = toml::from_str("[run]\nseed = 1\n").unwrap();
        assert_eq!(c.train.last_block, LastBlockChoice::Auto);
        assert!(
            !c.to_toml().unwrap().contains("last_block"),
            "files at the default stay as they were"
        );
        let t: TrainConfig = toml::from_str("[train]\nlast_block = \"state_tokens\"\n").unwrap();
        assert_eq!(t.train.last_block, LastBlockChoice::StateTokens);
        assert!(t.to_toml().unwrap().contains("last_block = \"state_tokens\""));
        assert!(toml::from_str::<TrainConfig>("[train]\nlast_block = \"some\"\n").is_err());
        // `auto`: the state tokens on CUDA and in batched packs, every token in a solo CPU run.
        let auto = LastBlockChoice::Auto;
        assert!(auto.state_tokens(true, false) && auto.state_tokens(false, true));
        assert!(!auto.state_tokens(false, false));
        assert!(!LastBlockChoice::AllTokens.state_tokens(true, true));
        assert!(LastBlockChoice::StateTokens.state_tokens(false, false));
    }

    #[test]
    fn optim_flat_defaults_to_auto_and_is_written_only_when_set() {
        let c: TrainConfig = toml::from_str("[optim]\nlearning_rate = 1e-3\n").unwrap();
        assert_eq!(c.optim.flat, FlatOptim::Auto);
        assert!(!c.to_toml().unwrap().contains("flat"), "files at the default stay as they were");
        let on: TrainConfig = toml::from_str("[optim]\nflat = \"on\"\n").unwrap();
        assert_eq!(on.optim.flat, FlatOptim::On);
        assert!(on.to_toml().unwrap().contains("flat = \"on\""));
        assert_eq!(toml::from_str::<TrainConfig>(&on.to_toml().unwrap()).unwrap(), on);
        assert!((FlatOptim::Auto.use_flat(true), FlatOptim::Auto.use_flat(false)) == (true, false));
        assert!(toml::from_str::<TrainConfig>("[optim]\nflat = \"yes\"\n").is_err());
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

    #[test]
    fn each_method_writes_and_checks_only_its_sections() {
        let mut c = TrainConfig::default();
        c.macaw.width = 0;
        // Prompt-DT: no [macaw] written, and its (invalid) MACAW settings are not checked.
        let text = c.to_toml().unwrap();
        assert!(!text.contains("[macaw]") && text.contains("[model]"), "{text}");
        c.validate().unwrap();
        // A Prompt-DT config.toml written before, with a [macaw] section, still loads.
        let old: TrainConfig =
            toml::from_str("[run]\nmethod = \"prompt-dt\"\n[macaw]\nwidth = 8\n").unwrap();
        assert_eq!((old.run.method, old.macaw.width), (Method::PromptDt, 8));
        old.validate().unwrap();

        // MACAW: [macaw] written and checked; the transformer's settings are not checked.
        c.run.method = Method::Macaw;
        assert!(c.to_toml().unwrap().contains("[macaw]"));
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("macaw.width"), "{e}");
        c.macaw.width = 8;
        c.model.hidden_size = 0;
        c.optim.learning_rate = f64::NAN;
        c.sampler.k = 0;
        c.validate().unwrap();
        let back: TrainConfig = toml::from_str(&c.to_toml().unwrap()).unwrap();
        assert_eq!(back.macaw, c.macaw);
        c.run.method = Method::MtOrl;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("model.hidden_size") && e.contains("optim.learning_rate"), "{e}");
        assert!(e.contains("sampler.k"), "{e}");
    }
}
