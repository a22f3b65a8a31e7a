//! A pack directory (`promptdt train --pack`): `pack.json`, the pack's record (each run's
//! directory and configuration, the engine: `pdt_rundir::pack`), written before any run is
//! created, and one ordinary run directory per run beside it. With the record, a pack killed at
//! any moment (even before some of its runs had a directory) resumes from its directory alone.

use crate::run::{prepare_pack, run_pack, train_pack, PackOptions, PackRun};
use pdt_base::fs::write_atomic;
use pdt_rundir::config::TrainConfig;
use pdt_rundir::pack::{is_pack_dir, Engine, PackRecord, PackRecordRun, PACK_JSON};
use pdt_train::run::{RunError, TrainSummary};
use std::path::{Component, Path, PathBuf};

/// Starts a pack of `configs` in the new pack directory `out`: `pack.json`, then each run in
/// `out/<method>-<env>-seed<seed>`. `opts.resume` must be false (see [`resume_pack_dir`]).
pub fn train_pack_dir(
    mut configs: Vec<TrainConfig>,
    out: &Path,
    opts: PackOptions<'_>,
) -> Result<Vec<Result<TrainSummary, RunError>>, RunError> {
    if is_pack_dir(out) {
        return Err(RunError::invalid(
            out.display(),
            format!(
                "already holds a pack; resume it (`promptdt train --resume {}`) or pick another \
                 --out",
                out.display()
            ),
        ));
    }
    // A pack directory holds its runs in subdirectories; one that is itself a run's directory
    // would mix the two (`train --config` refuses the same --out).
    let solo = pdt_rundir::RunDir::at(out);
    if let Some(file) = [solo.info_path(), solo.config_path()].into_iter().find(|f| f.is_file()) {
        return Err(RunError::invalid(
            out.display(),
            format!(
                "holds a run ({} is there): a pack directory holds its runs in subdirectories \
                 of its own; pick another --out",
                file.display()
            ),
        ));
    }
    let mut runs = Vec::with_capacity(configs.len());
    for cfg in &mut configs {
        // Recorded absolute, so the pack resumes from any directory.
        cfg.data.dir = pdt_train::setup::absolute(&cfg.data.dir);
        let family = pdt_envs::family(&cfg.env.name)?;
        let name = cfg.run_name(family.name());
        if runs.iter().any(|r: &PackRecordRun| r.dir == name) {
            return Err(RunError::invalid(
                "the pack's runs",
                format!(
                "two runs of the pack are {name} (method, environment and seed): each run of a \
                 pack needs its own; give them different seeds or train them in separate packs"
            ),
            ));
        }
        runs.push(PackRecordRun { dir: name, config: cfg.to_toml()? });
    }
    let engine = match opts.engine {
        Some(e) => e,
        None => {
            let first = configs.first().map(|c| c.run.device);
            let device = first.map(pdt_torch::device::resolve).transpose()?;
            Engine::default_for(device.is_some_and(|d| d != tch::Device::Cpu))
        }
    };
    let members = runs.iter().map(|r| out.join(&r.dir)).zip(configs);
    let members = members.map(|(dir, config)| PackRun { config, dir }).collect();
    let opts = PackOptions { resume: false, engine: Some(engine), ..opts };
    // Checked and built before anything is written: a refused pack leaves no record behind.
    let ready = prepare_pack(members, &opts)?;
    let record = PackRecord { engine: engine.name().into(), eval: None, runs };
    std::fs::create_dir_all(out).map_err(|source| RunError::Io { path: out.into(), source })?;
    let path = out.join(PACK_JSON);
    let text = serde_json::to_string_pretty(&record)
        .map_err(|e| RunError::Corrupt { path: path.clone(), message: e.to_string() })?;
    write_atomic(&path, format!("{text}\n").as_bytes())
        .map_err(|source| RunError::Io { path: path.clone(), source })?;
    Ok(run_pack(ready, opts))
}

/// Resumes the pack in `dir` (its `pack.json`): each run from its last checkpoint, a run the pack
/// never got to create from its recorded configuration. The engine is the recorded one unless
/// `opts.engine` says otherwise.
pub fn resume_pack_dir(
    dir: &Path,
    opts: PackOptions<'_>,
) -> Result<Vec<Result<TrainSummary, RunError>>, RunError> {
    let path = dir.join(PACK_JSON);
    let record: PackRecord = pdt_rundir::read_json(&path)?;
    let recorded: Engine = record
        .engine
        .parse()
        .map_err(|e: String| RunError::Corrupt { path: path.clone(), message: e })?;
    let mut runs = Vec::with_capacity(record.runs.len());
    for r in &record.runs {
        let config: TrainConfig = toml::from_str(&r.config).map_err(|e| RunError::Corrupt {
            path: path.clone(),
            message: format!("the configuration of run {}: {e}", r.dir),
        })?;
        let given = PathBuf::from(&r.dir);
        // A name inside the pack directory (`train --pack`), or an absolute path (`reproduce
        // --pack`, whose runs live in the plan's tree); nothing that climbs out of either.
        let single = given.components().count() == 1;
        let plain =
            given.components().all(|c| matches!(c, Component::Normal(_) | Component::RootDir));
        if !plain || !(given.is_absolute() || single) {
            return Err(RunError::Corrupt {
                path: path.clone(),
                message: format!(
                    "run directory `{}` is neither a name inside the pack nor an absolute path",
                    r.dir
                ),
            });
        }
        runs.push(PackRun { config, dir: dir.join(given) });
    }
    let engine = Some(opts.engine.unwrap_or(recorded));
    // (`record.eval`, from a pack started with `--pack-eval`, is ignored: evaluations are apart.)
    train_pack(runs, PackOptions { resume: true, engine, ..opts })
}
