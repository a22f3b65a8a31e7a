//! `promptdt data inspect | convert | report | import`.

use crate::args::{ConvertArgs, DataReportArgs, ImportArgs, InspectArgs};
use anyhow::{bail, Context, Result};
use pdt_data::flat::{FlatSteps, PromptRule};
use pdt_data::native::{task_file_stem, write_task_dataset, FileMeta};
use std::path::Path;

/// Per file: trajectories, steps, dims, dtypes, returns; a table or JSON.
pub fn inspect(a: &InspectArgs) -> Result<()> {
    let reports = pdt_data::inspect::inspect_path(&a.path)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&reports)?);
    } else {
        out_inline!("{}", pdt_data::inspect::render_table(&reports));
    }
    Ok(())
}

/// The reference release's pickles into safetensors, one line per file.
pub fn convert(a: &ConvertArgs) -> Result<()> {
    let files = pdt_data::multitask::convert_reference_dir(&a.src, &a.dst)?;
    for f in &files {
        out!("{f}");
    }
    out!("converted {} files into {}", files.len(), a.dst.display());
    Ok(())
}

/// Our datasets beside the reference's: the tables, then the files written.
pub fn report(a: &DataReportArgs) -> Result<()> {
    let cfg = pdt_report::DatasetReportConfig {
        out_dir: a.out.clone().unwrap_or_else(|| a.ours.join("report")),
        ours: a.ours.clone(),
        reference: a.reference.clone(),
    };
    let summary = pdt_report::dataset_report(&cfg)?;
    for f in &summary.families {
        out_inline!("{}", f.markdown);
    }
    for w in &summary.warnings {
        eprintln!("warning: {w}");
    }
    for f in &summary.files {
        out!("wrote {}", f.display());
    }
    Ok(())
}

/// A flat `.npz` or HDF5 file of step arrays with a task column into a suite's (or family's) per-task
/// datasets and prompt sets: everything read and checked before the first file is written.
pub fn import(a: &ImportArgs) -> Result<()> {
    let family = pdt_envs::family(&a.env)?;
    let preset = family.preset();
    let name = family.name().to_owned();
    let rule: PromptRule = a.prompt_rule.parse().map_err(anyhow::Error::msg)?;
    if let Some(id) = &a.minari {
        return import_minari(a, id);
    }
    let field = a.task_field.as_deref().unwrap_or("task_ids");
    let (file, flat) = match (&a.npz, &a.hdf5) {
        (Some(npz), _) => (npz, read_flat_npz(npz, preset.obs_dim, preset.act_dim, field)?),
        (None, Some(h5)) => {
            let read =
                pdt_data::flat_hdf5::read_flat_hdf5(h5, preset.obs_dim, preset.act_dim, field)?;
            if !read.ignored.is_empty() {
                out!("{}: left out (not step arrays): {}", h5.display(), read.ignored.join(", "));
            }
            (h5, read.steps)
        }
        (None, None) => bail!("give the data: --npz FILE, --hdf5 FILE or --minari ID"),
    };
    let tasks = flat.split_by_task(file, family.num_tasks())?;
    if !a.out.is_dir() {
        std::fs::create_dir_all(&a.out)
            .with_context(|| format!("creating the output directory {}", a.out.display()))?;
    }
    let prompt_mode = format!("prompt-{}", a.mode);
    let mut steps = 0;
    for (&task, ds) in &tasks {
        for (mode, set) in [(a.mode.as_str(), ds.clone()), (prompt_mode.as_str(), rule.prompts(ds))]
        {
            let path = a.out.join(format!("{}.safetensors", task_file_stem(&name, task, mode)));
            write_task_dataset(&path, &set, &FileMeta::new(&name, task, mode))?;
        }
        steps += ds.num_steps();
    }
    let missing: Vec<String> =
        (0..family.num_tasks()).filter(|t| !tasks.contains_key(t)).map(|t| t.to_string()).collect();
    out!(
        "imported {steps} steps of {} tasks of {name} into {} ({} and {prompt_mode} files; prompts: {})",
        tasks.len(),
        a.out.display(),
        a.mode,
        a.prompt_rule
    );
    if !missing.is_empty() {
        out!("no data for tasks {} (a split that names them cannot train yet)", missing.join(", "));
    }
    Ok(())
}

/// A Minari dataset through `promptdt.minari_io` in Python (Minari is a Python library; its one
/// reader is `promptdt.import_minari`, which checks and writes through this library's code).
fn import_minari(a: &ImportArgs, id: &str) -> Result<()> {
    let mut python = pdt_envs::worker::default_python();
    if pdt_envs::suite::is_suite_path(&a.env) {
        let suite = pdt_envs::suite::SuiteFamily::load(Path::new(&a.env))?;
        if let Some(spec) = suite.environment() {
            python =
                pdt_envs::worker::python(spec, suite.path().parent().unwrap_or(Path::new(".")));
        }
    }
    let mut cmd = std::process::Command::new(&python);
    cmd.args(["-m", "promptdt.minari_io", id]).arg(&a.out).args(["--env", &a.env]);
    cmd.args(["--mode", &a.mode, "--prompt-rule", &a.prompt_rule]);
    if let Some(f) = &a.task_field {
        cmd.args(["--task-field", f]);
    }
    if let Some(t) = &a.task {
        cmd.args(["--task", t]);
    }
    let run = cmd.output().with_context(|| {
        format!(
            "starting {} (a Python with promptdt and minari reads Minari datasets)",
            python.display()
        )
    })?;
    let stderr = String::from_utf8_lossy(&run.stderr);
    if !run.status.success() {
        let why = stderr.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("no message");
        bail!(
            "importing Minari dataset {id} with {}: {}",
            python.display(),
            why.trim_start_matches("error: ")
        );
    }
    let files = String::from_utf8_lossy(&run.stdout);
    for f in files.lines() {
        out!("{f}");
    }
    out!("imported Minari dataset {id} into {} ({} files)", a.out.display(), files.lines().count());
    Ok(())
}

/// The six arrays of a flat dataset from `path`, each of the shape the suite's sizes give.
fn read_flat_npz(
    path: &Path,
    obs_dim: usize,
    act_dim: usize,
    task_field: &str,
) -> Result<FlatSteps> {
    let arrays = tch::Tensor::read_npz(path)
        .with_context(|| format!("{}: not a readable .npz of numeric arrays", path.display()))?;
    let mut by_name: std::collections::BTreeMap<String, tch::Tensor> = arrays.into_iter().collect();
    let mut take = |field: &str, width: Option<usize>| -> Result<tch::Tensor> {
        let t = by_name.remove(field).ok_or_else(|| {
            anyhow::anyhow!(
                "{}: no array `{field}` (a flat dataset has observations, actions, rewards, \
                 terminals, timeouts and a task column, `{task_field}`)",
                path.display()
            )
        })?;
        let shape: Vec<u64> = t.size().iter().map(|&d| d as u64).collect();
        pdt_data::flat::check_column_shape(path, field, &shape, width)?;
        Ok(t.flatten(0, -1))
    };
    let floats = |t: tch::Tensor| -> Result<Vec<f32>> {
        Ok(Vec::<f32>::try_from(t.to_kind(tch::Kind::Float))?)
    };
    let flags = |t: tch::Tensor| -> Result<Vec<bool>> {
        Ok(Vec::<bool>::try_from(t.to_kind(tch::Kind::Bool))?)
    };
    let observations = floats(take("observations", Some(obs_dim))?)?;
    let actions = floats(take("actions", Some(act_dim))?)?;
    let rewards = floats(take("rewards", None)?)?;
    let terminals = flags(take("terminals", None)?)?;
    let timeouts = flags(take("timeouts", None)?)?;
    let ids = take(task_field, None)?;
    if ids.is_floating_point() {
        bail!(
            "{}: `{task_field}` holds {:?} values; expected whole numbers",
            path.display(),
            ids.kind()
        );
    }
    let task_ids = Vec::<i64>::try_from(ids.to_kind(tch::Kind::Int64))?;
    if let Some(extra) = by_name.keys().next() {
        bail!(
            "{}: unknown array `{extra}` (a flat dataset has observations, actions, rewards, \
             terminals, timeouts and a task column, `{task_field}`)",
            path.display()
        );
    }
    Ok(FlatSteps {
        obs_dim,
        act_dim,
        observations,
        actions,
        rewards,
        terminals,
        timeouts,
        task_ids,
    })
}
