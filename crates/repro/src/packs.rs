//! `reproduce --pack N`: a plan's runs grouped into packs (`docs/packs.md`), each pack one
//! `promptdt train` process training its runs in lockstep, each run in its ordinary directory.
//!
//! Runs share a pack when they are of one family, one model shape, one device and one data
//! directory (so a moved tree's `--data` applies to all), and are of a method that packs
//! (`Method::packs`: not MACAW, which trains alone).

use crate::plan::RunSpec;
use crate::ReproError;
use pdt_rundir::pack::{Engine, PackRecord, PackRecordRun, PACK_JSON};
use std::path::{Path, PathBuf};

/// What runs must have in common to share a pack; `None` for a run that trains alone.
pub fn pack_key(spec: &RunSpec) -> Option<String> {
    let c = &spec.config;
    if !c.run.method.packs() {
        return None;
    }
    let model = toml::to_string(&c.model).ok()?;
    Some(format!(
        "{}\n{:?}\n{}\n{model}",
        c.env.name,
        c.run.device,
        spec.data.dir.to_string_lossy()
    ))
}

/// The plan's runs (in plan order) cut into groups: runs of one pack key, up to `size` each, in
/// the order of their first run; a run that trains alone is a group of one.
pub fn group<'a>(runs: &[&'a RunSpec], size: usize) -> Vec<Vec<&'a RunSpec>> {
    let mut groups: Vec<(Option<String>, Vec<&'a RunSpec>)> = Vec::new();
    for &r in runs {
        let key = pack_key(r).filter(|_| size > 1);
        let open = groups.iter_mut().find(|(k, g)| key.is_some() && *k == key && g.len() < size);
        match open {
            Some((_, g)) => g.push(r),
            None => groups.push((key, vec![r])),
        }
    }
    groups.into_iter().map(|(_, g)| g).collect()
}

/// Writes the pack record of `runs` (absolute run directories, their configurations) into a pack
/// directory under `out/packs/`, named after its first run, and returns that directory: `train
/// --resume` of it starts each new run and resumes each partial one.
pub fn write_pack_dir(
    out: &Path,
    runs: &[&RunSpec],
    engine: Engine,
) -> Result<PathBuf, ReproError> {
    let first = runs.first().ok_or_else(|| ReproError::Invalid("an empty pack".into()))?;
    let name: String = first
        .key
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' })
        .collect();
    let dir = out.join("packs").join(format!("{name}-x{}", runs.len()));
    let mut members = Vec::with_capacity(runs.len());
    for r in runs {
        let config =
            r.config.to_toml().map_err(|e| ReproError::Invalid(format!("run {}: {e}", r.key)))?;
        let abs = std::path::absolute(&r.dir)
            .map_err(|e| ReproError::Io { path: r.dir.clone(), source: e })?;
        members.push(PackRecordRun { dir: abs.to_string_lossy().into_owned(), config });
    }
    let record = PackRecord { engine: engine.name().into(), eval: None, runs: members };
    let text = serde_json::to_string_pretty(&record)
        .map_err(|e| ReproError::Invalid(format!("pack record: {e}")))?;
    let path = dir.join(PACK_JSON);
    std::fs::create_dir_all(&dir).map_err(|e| ReproError::Io { path: dir.clone(), source: e })?;
    pdt_base::fs::write_atomic(&path, format!("{text}\n").as_bytes())
        .map_err(|e| ReproError::Io { path, source: e })?;
    Ok(dir)
}
