//! The error of a run: its set-up, training, checkpoints and evaluation.

use pdt_data::DataError;
use pdt_envs::EnvError;
use pdt_eval::EvalError;
use pdt_model::checkpoint::CheckpointError;
use pdt_prompt::SamplerError;
use pdt_rundir::config::ConfigError;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Sampler(#[from] SamplerError),
    #[error(transparent)]
    Eval(#[from] EvalError),
    #[error(transparent)]
    Strategy(#[from] pdt_prompt::StrategyError),
    /// An `[eval.adapt]` setting out of range (the message names it).
    #[error(transparent)]
    Adapt(#[from] pdt_rundir::config::AdaptError),
    /// MACAW's configuration or step refused (the message names the setting).
    #[error(transparent)]
    Macaw(#[from] pdt_macaw::MacawError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Device(#[from] pdt_torch::device::DeviceError),
    #[error(transparent)]
    Matmul(#[from] pdt_torch::device::MatmulError),
    /// A run-directory file unreadable, malformed or unwritable (the error names it).
    #[error(transparent)]
    RunDir(#[from] pdt_rundir::RunDirError),
    /// The run's data, configuration or files (`pdt_run::RunData`, `pdt_run::files`).
    #[error(transparent)]
    Load(#[from] pdt_run::LoadError),
    /// A test task's adaptation, made by the acting policy's runtime (`pdt_policy::adapt`).
    #[error(transparent)]
    Policy(#[from] pdt_policy::PolicyError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Corrupt { path: PathBuf, message: String },
    /// A setting, flag, file or part of a run refused: `what` names it (`--iterations`,
    /// `eval.adapt`, a run directory, `pack`), `why` says what is wrong with it and what to do.
    #[error("{what}: {why}")]
    Invalid { what: String, why: String },
    /// Another promptdt process holds the run directory (`lock` is its lock file): wait for it,
    /// or train elsewhere.
    #[error(
        "{} is in use by another promptdt process (it holds {}); wait for it to finish, or pick \
         another --out",
        dir.display(),
        lock.display()
    )]
    Busy { dir: PathBuf, lock: PathBuf },
    /// Training diverged (a non-finite loss or gradient norm): resuming would repeat the same
    /// steps, so the configuration must change.
    #[error("{}: {message}", dir.display())]
    Diverged { dir: PathBuf, message: String },
    /// A broken promise inside the library (a pack engine's protocol, a thread that panicked),
    /// not a fault of the input.
    #[error("{0}")]
    Internal(String),
    /// A run of a pack failed: `dir` is the run, `source` why.
    #[error("run {} of the pack: {source}", dir.display())]
    InPack { dir: PathBuf, source: Box<RunError> },
    /// A stop was asked for ([`crate::run::TrainOptions::interrupt`]) during `iteration`; nothing
    /// of it was written.
    #[error(
        "{}: training interrupted during iteration {iteration}; resume goes on from the run's \
         last checkpoint",
        dir.display()
    )]
    Interrupted { dir: PathBuf, iteration: u64 },
}

/// Maps an I/O error on `path` to [`RunError::Io`], naming the path.
pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RunError + '_ {
    move |source| RunError::Io { path: path.into(), source }
}

/// Test time's refusals and failures (`pdt_eval::testtime`) as a run's: each by its kind, the
/// message unchanged.
impl From<pdt_eval::testtime::TestTimeError> for RunError {
    fn from(e: pdt_eval::testtime::TestTimeError) -> Self {
        use pdt_eval::testtime::TestTimeError as T;
        match e {
            T::Input(m) | T::Failed(m) => RunError::invalid("test time", m),
            T::Sampler(e) => RunError::Sampler(e),
            T::Strategy(e) => RunError::Strategy(e),
            T::Env(e) => RunError::Env(e),
            T::Eval(e) => RunError::Eval(e),
        }
    }
}

impl RunError {
    /// [`RunError::Invalid`]: `what` refused because `why`.
    pub fn invalid(what: impl std::fmt::Display, why: impl std::fmt::Display) -> Self {
        RunError::Invalid { what: what.to_string(), why: why.to_string() }
    }
}
