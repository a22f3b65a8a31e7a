use std::path::PathBuf;

/// Why a run's configuration, data or files cannot be used: each names the file, field or value at
/// fault. The trainer and an acting policy both meet these, so they are defined once, here.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error(transparent)]
    Config(#[from] pdt_rundir::config::ConfigError),
    #[error(transparent)]
    Data(#[from] pdt_data::DataError),
    #[error(transparent)]
    Env(#[from] pdt_envs::EnvError),
    #[error(transparent)]
    Sampler(#[from] pdt_prompt::SamplerError),
    #[error(transparent)]
    RunDir(#[from] pdt_rundir::RunDirError),
    #[error("{path}: {message}")]
    Corrupt { path: PathBuf, message: String },
    #[error("{}: not a run directory (no config.toml)", .0.display())]
    NotARunDir(PathBuf),
    #[error("{}: no checkpoint yet (train first)", .0.display())]
    NoCheckpoint(PathBuf),
    /// The run's configuration and data do not fit together (the trainer's checks).
    #[error("{0}")]
    Invalid(String),
}
