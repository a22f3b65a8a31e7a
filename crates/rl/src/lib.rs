//! Online RL for making Prompt-DT's offline datasets: SAC and TD3 (one flat module each), a
//! shared replay buffer and flat-parameter networks, a resumable training loop for one
//! task-conditioned agent per family, and the dataset generator (expert / medium / random data and
//! prompt sets, in the native format with a dataset card).
//!
//! - [`sac`], [`td3`]: the algorithms.
//! - [`nets`]: MLPs whose parameters are one flat tensor; Adam on it.
//! - [`buffer`]: the replay buffer.
//! - [`agent`]: task conditioning, the `Agent` enum, action noise on the host.
//! - [`policy`]: exported actors (the pretrained experts) as safetensors.
//! - [`rollout`]: many episodes stepped together with one batched actor forward per step.
//! - [`train`]: the training loop, checkpoints, snapshots.
//! - [`combine`]: per-task experts picked from the snapshots of one or more runs.
//! - [`datasets`]: expert / medium / random datasets and prompt sets from exported actors.
//! - [`display`]: the summaries `promptdt collect` and `promptdt agent combine` print.

pub mod agent;
pub mod bench;
pub mod buffer;
pub mod combine;
pub mod datasets;
pub mod display;
pub mod nets;
pub mod overrides;
pub mod policy;
pub mod rollout;
pub mod sac;
pub mod td3;
pub mod train;

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum RlError {
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error(transparent)]
    Env(#[from] pdt_envs::EnvError),
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A checkpoint or policy file that cannot be used; `path` names it.
    #[error("{}: {message}", path.display())]
    File { path: PathBuf, message: String },
    #[error("cannot write {}: {source}", path.display())]
    Data {
        path: PathBuf,
        #[source]
        source: pdt_data::DataError,
    },
    /// The run directory already holds a run and `resume` was not asked for.
    #[error("{} already holds a training run: pass --resume to continue it, or choose another directory", path.display())]
    Exists { path: PathBuf },
    #[error("no checkpoint to resume in {}", path.display())]
    NoCheckpoint { path: PathBuf },
    #[error("training diverged: {0}")]
    Diverged(String),
    /// A stop was asked for (`datasets::DatasetConfig::interrupt`).
    #[error("collection interrupted: the files written so far are whole, the card was not written; collect again to finish")]
    Interrupted,
}

use pdt_base::seed::derive_seed;

/// A ChaCha8 generator for `(seed, stream, counter)`.
pub fn stream_rng(seed: u64, stream: u64, counter: u64) -> rand_chacha::ChaCha8Rng {
    use rand::SeedableRng;
    rand_chacha::ChaCha8Rng::seed_from_u64(derive_seed(seed, stream, counter))
}

/// Writes `bytes` to `path` atomically (temp file + fsync + rename; see
/// `pdt_data::native::write_bytes_atomically`).
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> Result<(), RlError> {
    pdt_data::native::write_bytes_atomically(path, bytes)
        .map_err(|source| RlError::Data { path: path.to_path_buf(), source })
}
