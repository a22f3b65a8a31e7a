//! The suite file as written: TOML read into plain structs, before any check. Tables whose errors
//! must name their place (`tasks[3]`, `splits.ood`, `environment`) are kept as raw TOML here and
//! read one by one in `check.rs`, so that a missing or unknown field inside them is reported with
//! its path rather than only a line number.

use serde::de::{Deserializer, MapAccess, Visitor};
use serde::Deserialize;
use std::fmt;

/// The top level of a suite file (`docs/your-own-tasks.md` documents every field).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSuite {
    pub name: String,
    pub obs_dim: i64,
    pub act_dim: i64,
    /// One bound for every dimension: actions lie in `[-action_bound, action_bound]`.
    #[serde(default)]
    pub action_bound: Option<f64>,
    #[serde(default)]
    pub action_low: Option<Vec<f64>>,
    #[serde(default)]
    pub action_high: Option<Vec<f64>>,
    pub max_ep_len: i64,
    pub rtg_scale: f64,
    #[serde(default)]
    pub target_return: Option<f64>,
    pub prompt_length: i64,
    #[serde(default)]
    pub render_fps: Option<i64>,
    #[serde(default)]
    pub success_reward: Option<f64>,
    pub tasks: Vec<toml::Value>,
    pub splits: OrderedTables,
    #[serde(default)]
    pub environment: Option<toml::Value>,
}

/// One `[[tasks]]` entry.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTask {
    pub name: String,
    #[serde(default)]
    pub params: Option<toml::Value>,
    #[serde(default)]
    pub target_return: Option<f64>,
    #[serde(default)]
    pub expert_return: Option<f64>,
    #[serde(default)]
    pub random_return: Option<f64>,
}

/// One `[splits.NAME]` table: the tasks trained on and the held-out ones, by name.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSplit {
    pub train: Vec<String>,
    pub test: Vec<String>,
}

/// A table's entries in the order the file writes them: the first split is the default one, and
/// `toml::Table` (a sorted map without toml's `preserve_order` feature) would lose that order.
#[derive(Debug, Default)]
pub(super) struct OrderedTables(pub Vec<(String, toml::Value)>);

impl<'de> Deserialize<'de> for OrderedTables {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Ordered;
        impl<'de> Visitor<'de> for Ordered {
            type Value = OrderedTables;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a table of named splits")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
                let mut entries = Vec::new();
                while let Some((k, v)) = map.next_entry::<String, toml::Value>()? {
                    entries.push((k, v));
                }
                Ok(OrderedTables(entries))
            }
        }
        d.deserialize_map(Ordered)
    }
}
