//! The vocabulary of collected datasets: which policy quality a file holds ([`Mode`], the `mode` in
//! `{env}-{task}-{mode}` file names) and which of a task's two sets an episode belongs to ([`Set`]).
//! Shared by the scripted collector (`pdt-envs`) and the RL agents' datasets (`pdt-rl`).

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

/// A collection policy of decreasing quality, and the dataset kind it produces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Expert,
    Medium,
    Random,
}

/// A mode name that is not one of [`Mode::ALL`]'s.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown mode {0:?} (known: expert, medium, random)")]
pub struct UnknownMode(pub String);

impl Mode {
    /// All modes, best first.
    pub const ALL: [Mode; 3] = [Mode::Expert, Mode::Medium, Mode::Random];

    /// The name used in file names and cards.
    pub fn name(self) -> &'static str {
        match self {
            Mode::Expert => "expert",
            Mode::Medium => "medium",
            Mode::Random => "random",
        }
    }

    /// Stable number of the mode in RNG keys: adding a mode must not change the others' data.
    pub fn rng_id(self) -> u32 {
        match self {
            Mode::Expert => 0,
            Mode::Medium => 1,
            Mode::Random => 2,
        }
    }
}

impl fmt::Display for Mode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Mode {
    type Err = UnknownMode;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Mode::ALL.into_iter().find(|m| m.name() == s).ok_or_else(|| UnknownMode(s.to_owned()))
    }
}

/// Which of a task's two sets an episode belongs to. Part of the RNG key, so P_i's episodes are
/// distinct from D_i's and do not change when the number of D_i's episodes does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Set {
    /// The main dataset D_i.
    Dataset,
    /// The prompt set P_i.
    Prompt,
}

impl Set {
    /// Stable number of the set in RNG keys.
    pub fn rng_id(self) -> u32 {
        match self {
            Set::Dataset => 0,
            Set::Prompt => 1,
        }
    }
}
