//! The native on-disk format: one plain [safetensors] file per (task, kind), plus an optional
//! `dataset.json` card per directory. The full specification is `docs/data-format.md`.
//!
//! A file `{env}-{index}-{mode}.safetensors` (named like the reference release's pickles, so the two
//! are interchangeable) holds the steps of all its episodes concatenated:
//!
//! | tensor           | dtype | shape          |
//! |------------------|-------|----------------|
//! | `observations`   | F32   | `[N, obs_dim]` |
//! | `actions`        | F32   | `[N, act_dim]` |
//! | `rewards`        | F32   | `[N]`          |
//! | `terminated`     | U8    | `[N]`          |
//! | `truncated`      | U8    | `[N]`          |
//! | `episode_starts` | I64   | `[E + 1]`      |
//!
//! `episode_starts` holds the offsets of the episodes: episode `e` is steps
//! `episode_starts[e]..episode_starts[e + 1]`; the first entry is 0 and the last is `N`. The
//! safetensors `__metadata__` map carries `format = "promptdt-trajectories"`, `format_version = "1"`
//! and, when known, `env`, `task_index` and `mode`.
//!
//! Everything a file needs is in the file: [`read_task_dataset`] never looks at the card.
//!
//! [safetensors]: https://github.com/huggingface/safetensors

use std::borrow::Cow;
use std::collections::HashMap;
use std::fs;
use std::io::Read;
use std::path::Path;

use safetensors::tensor::{Dtype, Metadata, SafeTensorError, View};
use serde::{Deserialize, Serialize};

use crate::{DataError, TaskDataset, Trajectory};

/// Value of the `format` metadata key.
pub const FORMAT_NAME: &str = "promptdt-trajectories";
/// Value of the `format_version` metadata key written by, and the only one understood by, this
/// crate.
pub const FORMAT_VERSION: &str = "1";
/// File extension of native trajectory files (without the dot).
pub const FILE_EXTENSION: &str = "safetensors";
/// Name of the optional per-directory dataset card.
pub const CARD_FILE_NAME: &str = "dataset.json";
/// Value of the card's `format` key.
pub const CARD_FORMAT_NAME: &str = "promptdt-dataset";
/// Largest safetensors JSON header this reader accepts. Headers written here are well under 1 KiB
/// (six tensors and five short strings); the bound stops a corrupt or hostile length prefix from
/// making us read or parse a huge header. The safetensors crate's own bound is 100 MB.
pub const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Tensor names, as they appear in the file.
pub mod tensor_names {
    pub const OBSERVATIONS: &str = "observations";
    pub const ACTIONS: &str = "actions";
    pub const REWARDS: &str = "rewards";
    pub const TERMINATED: &str = "terminated";
    pub const TRUNCATED: &str = "truncated";
    pub const EPISODE_STARTS: &str = "episode_starts";
}
use tensor_names::*;

/// Metadata keys, as they appear in the safetensors `__metadata__` map.
pub mod meta_keys {
    pub const FORMAT: &str = "format";
    pub const FORMAT_VERSION: &str = "format_version";
    pub const ENV: &str = "env";
    pub const TASK_INDEX: &str = "task_index";
    pub const MODE: &str = "mode";
}

/// What a file says about itself in its `__metadata__`: which task and which kind of set it holds.
/// Every field is optional: a file stays readable without them.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileMeta {
    /// Environment family, e.g. `cheetah_vel`.
    pub env: Option<String>,
    /// Task index within the family, e.g. `2`.
    pub task_index: Option<usize>,
    /// Kind of set, e.g. `expert`, `medium`, `prompt-expert`.
    pub mode: Option<String>,
}

impl FileMeta {
    /// All three fields known.
    pub fn new(env: impl Into<String>, task_index: usize, mode: impl Into<String>) -> Self {
        Self { env: Some(env.into()), task_index: Some(task_index), mode: Some(mode.into()) }
    }

    /// Parses a file name `{env}-{index}-{mode}.{ext}` (or a bare stem); `None` if it does not
    /// follow the convention. See [`parse_task_file_stem`].
    pub fn from_file_name(path: &Path) -> Option<Self> {
        let stem = path.file_stem()?.to_str()?;
        let (env, index, mode) = parse_task_file_stem(stem)?;
        Some(Self::new(env, index, mode))
    }

    /// The conventional file name `{env}-{index}-{mode}.safetensors`, when all fields are known.
    pub fn file_name(&self) -> Option<String> {
        match (&self.env, self.task_index, &self.mode) {
            (Some(env), Some(index), Some(mode)) => {
                Some(format!("{}.{FILE_EXTENSION}", task_file_stem(env, index, mode)))
            }
            _ => None,
        }
    }

    fn to_safetensors_map(&self) -> HashMap<String, String> {
        let mut map = HashMap::new();
        map.insert(meta_keys::FORMAT.to_owned(), FORMAT_NAME.to_owned());
        map.insert(meta_keys::FORMAT_VERSION.to_owned(), FORMAT_VERSION.to_owned());
        if let Some(env) = &self.env {
            map.insert(meta_keys::ENV.to_owned(), env.clone());
        }
        if let Some(index) = self.task_index {
            map.insert(meta_keys::TASK_INDEX.to_owned(), index.to_string());
        }
        if let Some(mode) = &self.mode {
            map.insert(meta_keys::MODE.to_owned(), mode.clone());
        }
        map
    }

    /// Reads the metadata map, checking `format` and `format_version` when present. Files that
    /// omit them (e.g. written by hand from Python) are taken as version 1.
    fn from_safetensors_map(
        path: &Path,
        map: Option<&HashMap<String, String>>,
    ) -> Result<Self, DataError> {
        let Some(map) = map else { return Ok(Self::default()) };
        if let Some(format) = map.get(meta_keys::FORMAT) {
            if format != FORMAT_NAME {
                return Err(format_err(
                    path,
                    format!(
                        "metadata `{}` is {format:?}, expected {FORMAT_NAME:?}: not a \
                         promptdt trajectory file",
                        meta_keys::FORMAT
                    ),
                ));
            }
        }
        if let Some(version) = map.get(meta_keys::FORMAT_VERSION) {
            if version != FORMAT_VERSION {
                return Err(format_err(
                    path,
                    format!(
                        "metadata `{}` is {version:?}; this reader understands only \
                         {FORMAT_VERSION:?}",
                        meta_keys::FORMAT_VERSION
                    ),
                ));
            }
        }
        let task_index = match map.get(meta_keys::TASK_INDEX) {
            None => None,
            Some(s) => Some(s.parse::<usize>().map_err(|_| {
                format_err(
                    path,
                    format!(
                        "metadata `{}` is {s:?}, expected a non-negative integer",
                        meta_keys::TASK_INDEX
                    ),
                )
            })?),
        };
        Ok(Self {
            env: map.get(meta_keys::ENV).cloned(),
            task_index,
            mode: map.get(meta_keys::MODE).cloned(),
        })
    }
}

/// The conventional stem `{env}-{index}-{mode}`, e.g. `cheetah_vel-2-prompt-expert`.
pub fn task_file_stem(env: &str, index: usize, mode: &str) -> String {
    format!("{env}-{index}-{mode}")
}

/// Splits a stem `{env}-{index}-{mode}` into its parts. Both `env` (`ML1-pick-place-v2`) and `mode`
/// (`prompt-expert`) may contain `-`, so the index is taken to be the *last* all-digit `-`-separated
/// piece that has a non-empty env before it and a non-empty mode after it.
pub fn parse_task_file_stem(stem: &str) -> Option<(String, usize, String)> {
    let pieces: Vec<&str> = stem.split('-').collect();
    // Last candidate position first; positions 0 and len-1 cannot work (empty env / mode).
    (1..pieces.len().saturating_sub(1)).rev().find_map(|i| {
        let piece = pieces[i];
        if piece.is_empty() || !piece.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        let index = piece.parse::<usize>().ok()?;
        let env = pieces[..i].join("-");
        let mode = pieces[i + 1..].join("-");
        (!env.is_empty() && !mode.is_empty()).then_some((env, index, mode))
    })
}

fn format_err(path: &Path, message: impl Into<String>) -> DataError {
    DataError::Format { path: path.to_path_buf(), message: message.into() }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DataError + '_ {
    move |source| DataError::Io { path: path.to_path_buf(), source }
}

fn shape_err(path: &Path, field: &'static str, expected: String, got: String) -> DataError {
    DataError::Shape { field, expected, got }.in_file(path)
}

// ---------------------------------------------------------------------------------------------
// Checks shared by the writer and the reader
// ---------------------------------------------------------------------------------------------

/// Checks one trajectory against the format's rules; the message names the array, the step and
/// (for vectors) the component at fault. The writer runs it so that it never writes a file the
/// reader would reject; the reader runs it on what it decoded.
fn check_trajectory(
    index: usize,
    t: &Trajectory,
    obs_dim: usize,
    act_dim: usize,
) -> Result<(), String> {
    let len = t.rewards.len();
    if len == 0 {
        return Err(format!("episode {index} is empty (every episode needs >= 1 step)"));
    }
    if t.obs_dim != obs_dim || t.act_dim != act_dim {
        return Err(format!(
            "episode {index} has obs_dim {}, act_dim {}; the dataset has {obs_dim}, {act_dim}",
            t.obs_dim, t.act_dim
        ));
    }
    for (name, got, want) in [
        (OBSERVATIONS, t.observations.len(), len * obs_dim),
        (ACTIONS, t.actions.len(), len * act_dim),
        (TERMINATED, t.terminated.len(), len),
        (TRUNCATED, t.truncated.len(), len),
    ] {
        if got != want {
            return Err(format!(
                "episode {index}: `{name}` has {got} elements, expected {want} ({len} steps)"
            ));
        }
    }
    check_finite(index, OBSERVATIONS, &t.observations, obs_dim)?;
    check_finite(index, ACTIONS, &t.actions, act_dim)?;
    check_finite(index, REWARDS, &t.rewards, 1)?;
    // A flag ends an episode, so it may only be set at its last step. (Both may be set there:
    // a time limit can coincide with a true termination.)
    for (name, flags) in [(TERMINATED, &t.terminated), (TRUNCATED, &t.truncated)] {
        if let Some(step) = flags[..len - 1].iter().position(|&f| f) {
            return Err(format!(
                "episode {index}: `{name}` is set at step {step} of {len}, but an episode's \
                 terminated/truncated flags are only allowed at its last step (split the episode \
                 there, or clear the flag)"
            ));
        }
    }
    Ok(())
}

fn check_finite(episode: usize, name: &str, values: &[f32], width: usize) -> Result<(), String> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => {
            let at = if width == 1 {
                format!("step {i}")
            } else {
                format!("step {}, component {}", i / width, i % width)
            };
            Err(format!(
                "episode {episode}: `{name}` is {} at {at}; the format stores finite values only",
                values[i]
            ))
        }
    }
}

mod card;
mod read;
mod write;

pub use card::{read_card, write_card, CardFile, CardTask, DatasetCard, ReturnStats};
pub use read::{read_file_meta, read_task_dataset, read_task_dataset_with_meta};
pub(crate) use write::write_atomically;
pub use write::{write_bytes_atomically, write_task_dataset};
