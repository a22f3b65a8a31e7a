//! A user's task suites in an experiment manifest (`[suites.<name>]`): a cell's `env` may name one,
//! so a user's experiment runs on a suite file (docs/your-own-tasks.md) with the same cells,
//! budgets, claims and report as the paper's families.
//!
//! A suite has no `collect` preset (its data come from the user's own collection step, e.g. a
//! script calling `promptdt.write_dataset`), so the manifest names where those data are, and
//! `reproduce` checks that they are there instead of collecting them.

use serde::Deserialize;
use std::path::{Path, PathBuf};

/// `[suites.<name>]`: a suite file and the directory of its data. `<name>` is what the cells'
/// `env` and the budgets' rules (`envs`) name; it is also the first part of the cells' ids (the
/// run directories' `runs/<name>/<method>/...`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuiteRef {
    /// The suite file; a relative path is taken from the manifest file's directory.
    pub file: PathBuf,
    /// The datasets and prompt sets of the suite's tasks (`{name}-{i}-{mode}.safetensors`, and
    /// `dataset.json` for normalised scores), written before `reproduce` runs; a relative path is
    /// taken from the manifest file's directory.
    pub data: PathBuf,
    /// How the data are made, in words (shown when they are missing): the user's command.
    #[serde(default)]
    pub collect: Option<String>,
}

impl SuiteRef {
    /// Both paths taken from `base` (the manifest file's directory) where relative.
    pub(crate) fn resolved(&self, base: &Path) -> SuiteRef {
        let at = |p: &Path| if p.is_absolute() { p.to_path_buf() } else { base.join(p) };
        SuiteRef { file: at(&self.file), data: at(&self.data), collect: self.collect.clone() }
    }

    /// The suite file's path as a family name (`pdt_envs::family` reads it as a suite file: it
    /// ends in `.toml`).
    pub fn family_name(&self) -> String {
        self.file.to_string_lossy().into_owned()
    }
}

/// Why `name` cannot name a suite in a manifest, if it cannot: it must read as a cell id's first
/// part (letters, digits, `_`, `-`) and must not be a built-in family's name (a cell naming it
/// would be ambiguous).
pub fn check_name(name: &str) -> Result<(), String> {
    let bad = |c: char| !(c.is_ascii_alphanumeric() || c == '_' || c == '-');
    if name.is_empty() || name.contains(bad) {
        return Err(format!("suites.{name:?}: use letters, digits, `_` and `-` in a suite's name"));
    }
    if pdt_envs::FAMILY_NAMES.contains(&name) {
        return Err(format!(
            "suites.{name}: `{name}` is a built-in family's name; give the suite another one"
        ));
    }
    Ok(())
}
