//! What a variant run is (docs/reproduce.md, "Variants"), apart from how it is run: its record
//! file, its base run, and its configuration (the base run's with the variant's `[eval]` merged
//! in). Read by the manifest, the plan and the registry; the evaluation itself is
//! `crate::variant`.

use pdt_rundir::config::TrainConfig;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// The record a finished variant evaluation writes last.
pub const VARIANT_JSON: &str = "variant.json";

/// `variant.json`: which run was evaluated, how, and what it wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VariantRecord {
    /// The base run's key (`<base id>/<budget>/seed<N>`).
    pub base: String,
    /// The table merged into the base run's `[eval]`.
    pub eval: toml::Table,
    /// The evaluation's own file in this directory (`eval_prompt_bandit.json`, ...).
    pub result_file: String,
    /// The base run's iteration whose weights were evaluated.
    pub iteration: u64,
    /// Wall time of the evaluation (the `promptdt eval` process), seconds.
    pub seconds: f64,
}

/// The base run of a variant's run, and the variant's override of its `[eval]`.
#[derive(Debug, Clone, PartialEq)]
pub struct BaseRun {
    pub key: String,
    pub dir: PathBuf,
    pub eval: toml::Table,
    /// Independent repeats of the evaluation (`promptdt eval --repeats`; the budget's
    /// `eval_repeats`, 1 = one evaluation as before).
    pub repeats: usize,
}

/// `config` with `eval` merged into its `[eval]` section (tables merged key by key, other values
/// replaced), read back as a configuration: an unknown key is an error naming it.
pub fn with_eval(config: &TrainConfig, eval: &toml::Table) -> Result<TrainConfig, String> {
    let mut v = config.to_toml_value().map_err(|e| e.to_string())?;
    let toml::Value::Table(t) = &mut v else {
        return Err("a configuration is a TOML table".into());
    };
    let section = t.entry("eval").or_insert(toml::Value::Table(toml::Table::new()));
    merge(section, eval);
    v.try_into().map_err(|e: toml::de::Error| format!("eval: {}", e.message()))
}

fn merge(into: &mut toml::Value, from: &toml::Table) {
    let toml::Value::Table(t) = into else {
        *into = toml::Value::Table(from.clone());
        return;
    };
    for (k, v) in from {
        if let (Some(old @ toml::Value::Table(_)), toml::Value::Table(sub)) = (t.get_mut(k), v) {
            merge(old, sub);
            continue;
        }
        t.insert(k.clone(), v.clone());
    }
}
