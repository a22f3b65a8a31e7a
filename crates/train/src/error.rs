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
    #[error("{0}")]
    Invalid(String),
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
            T::Input(m) | T::Failed(m) => RunError::Invalid(m),
            T::Sampler(e) => RunError::Sampler(e),
            T::Strategy(e) => RunError::Strategy(e),
            T::Env(e) => RunError::Env(e),
            T::Eval(e) => RunError::Eval(e),
        }
    }
}
