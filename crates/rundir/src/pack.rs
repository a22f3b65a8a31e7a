//! A pack directory's record (`pack.json`, `docs/packs.md`): each run's directory and starting
//! configuration and the engine that steps them. Here, with no libtorch, so that `reproduce`
//! writes a pack directory without linking the trainer that reads it.

use serde::{Deserialize, Serialize};
use std::path::Path;

/// The file of a pack directory that names its runs.
pub const PACK_JSON: &str = "pack.json";

/// `pack.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PackRecord {
    /// The engine the pack was started with (`batched` or `solo`); a resumed pack keeps it unless
    /// told otherwise, so its runs go on with the same arithmetic.
    pub engine: String,
    /// `together` or `apart`, in the record of a pack started with `--pack-eval`: read and
    /// ignored, since a pack's runs always evaluate apart, each with its own model (acting
    /// together measured no gain: `docs/packs.md`). Never written.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eval: Option<String>,
    pub runs: Vec<PackRecordRun>,
}

/// One run of `pack.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PackRecordRun {
    /// The run's directory: a name inside the pack directory, or an absolute path.
    pub dir: String,
    /// The configuration the run starts from (TOML, as its `config.toml`).
    pub config: String,
}

/// Whether `dir` is a pack directory (it has `pack.json`).
pub fn is_pack_dir(dir: &Path) -> bool {
    dir.join(PACK_JSON).is_file()
}

/// The engine that steps a pack.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Engine {
    /// One batched computation for all runs (stacked weights, batched products): the GPU's.
    Batched,
    /// Each run's ordinary solo step, one run after another: exact (a run trained through it is
    /// the same run trained alone, bit for bit).
    Solo,
}

impl Engine {
    pub fn name(self) -> &'static str {
        match self {
            Engine::Batched => "batched",
            Engine::Solo => "solo",
        }
    }

    /// The engine a pack gets when none is asked for: on a GPU the batched one (a step this small
    /// is bound by kernel launches there, which batching saves); on the CPU the solo one (exact;
    /// there a step is bound by arithmetic, which batching does not save).
    pub fn default_for(on_gpu: bool) -> Self {
        if on_gpu {
            Engine::Batched
        } else {
            Engine::Solo
        }
    }
}

impl std::str::FromStr for Engine {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "batched" => Ok(Engine::Batched),
            "solo" => Ok(Engine::Solo),
            _ => Err(format!("unknown pack engine `{s}` (batched or solo)")),
        }
    }
}
