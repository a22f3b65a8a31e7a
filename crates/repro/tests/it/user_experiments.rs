//! A user's experiment (a manifest file of their own, on their task suite) archived in the results
//! registry is rendered in RESULTS.md after the paper's experiments, read from the manifest its
//! archives record (`provenance.json`'s `manifest`, written by `results add`): its title, its
//! cells' table and its claims' verdicts. A manifest that is gone, one that now names another
//! experiment, and an archive of a user experiment that records no manifest are errors naming the
//! archive and the file, never a section dropped without a word.
//!
//! The runs are archived by `registry::add` from run directories written here with the run
//! directory's own writers: pdt-repro does not link the trainer, and the toy suite declares no
//! environment, so a real run of it has no return to archive (it is evaluated offline).
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_repro::registry::{self, AddOptions, ProvenanceFlags};
use pdt_repro::render::render;
use pdt_repro::{Manifest, PlanOptions};
use pdt_rundir::{EvalLine, Latest, MetricsLine, RunDir, RunInfo, RunStats};
use std::path::{Path, PathBuf};

const SUITE: &str = include_str!("../../../../examples/toy_line/suite.toml");

const MANIFEST: &str = r#"
name = "toy_exp"
title = "Toy line: Prompt-DT against MT-ORL"
description = "A user's experiment on the toy suite's held-out goals."
layout = "curves"

[suites.toy]
file = "suite.toml"
data = "data"

[[claims]]
text = "Prompt-DT beats MT-ORL on the held-out goals"
kind = "better"
a = "toy-main/prompt-dt"
b = "toy-main/mt-orl"

[budgets.smoke]
note = "two iterations of two steps"
iterations = 2
steps_per_iteration = 2
test_eval_interval = 1
seeds = 1

[[cells]]
env = "toy"
split = "main"
method = "prompt-dt"
row = "Prompt-DT"

[[cells]]
env = "toy"
split = "main"
method = "mt-orl"
row = "MT-ORL"
"#;

/// A finished run of `key` with the configuration the plan gives it, as the trainer lays one out:
/// evaluated after iterations 1 and 2 on the held-out goals g3 and g4 (task 3's return `ret`, task
/// 4's one less).
fn write_run(dir: &Path, config: &pdt_rundir::config::TrainConfig, method: &str, ret: f64) {
    let run = RunDir::at(dir);
    run.create_dir().unwrap();
    std::fs::create_dir_all(run.checkpoints_dir()).unwrap();
    run.write_config(config).unwrap();
    run.write_info(&RunInfo {
        name: format!("{method}-toy-seed0"),
        method: method.into(),
        env: "toy_line".into(),
        seed: 0,
        task_split: "main".into(),
        created: "unix:1796649604".into(),
        promptdt_version: "0.1.0".into(),
        loss_metric: None,
        pack: None,
    })
    .unwrap();
    run.write_stats(&RunStats {
        obs_dim: 2,
        act_dim: 1,
        state_mean: vec![0.0, 0.0],
        state_std: vec![1.0, 1.0],
        rtg_scale: 10.0,
        target_return: 10.0,
        horizon: 10,
        train_tasks: vec![0, 1, 2],
        test_tasks: vec![3, 4],
        train_data_fingerprint: String::new(),
        test_data_fingerprint: String::new(),
    })
    .unwrap();
    let mut evals = Vec::new();
    let mut metrics = Vec::new();
    for iteration in 1..=2u64 {
        for (task, r) in [(3, ret), (4, ret - 1.0)] {
            evals.push(EvalLine {
                iteration,
                step: 2 * iteration,
                eval_on: "test".into(),
                task: format!("toy_line-{task}"),
                task_index: task,
                return_mean: r - 2.0 + iteration as f64,
                return_std: 0.0,
                length_mean: 10.0,
                episodes: 1,
                target_return: 10.0,
                success_rate: None,
                adaptation: None,
            });
        }
        let values = [("train/action_loss".to_string(), 0.5 / iteration as f64)].into();
        metrics.push(MetricsLine { iteration, step: 2 * iteration, elapsed_s: 1.0, values });
    }
    run.append_eval_lines(&evals).unwrap();
    run.append_metrics(&metrics).unwrap();
    run.write_latest(&Latest {
        step: 4,
        iteration: 2,
        model: Latest::model_name(4),
        state: Latest::state_name(4),
        keep: true,
    })
    .unwrap();
}

/// `root/exp/manifest.toml` beside the toy suite, both cells' runs archived from it by
/// `results add` into `root/results`. Returns the manifest's path and the registry.
fn archived(root: &Path) -> (PathBuf, PathBuf) {
    let exp = root.join("exp");
    std::fs::create_dir_all(&exp).unwrap();
    // The toy suite declares g3's expert and random returns only; a claim is judged on every
    // held-out goal's normalised score, so g4's are declared too.
    let g4 = "params = { goal = 1.0 }";
    assert!(SUITE.contains(g4));
    let suite = SUITE.replace(g4, &format!("{g4}\nexpert_return = 9.0\nrandom_return = 1.0"));
    std::fs::write(exp.join("suite.toml"), suite).unwrap();
    let manifest = exp.join("manifest.toml");
    std::fs::write(&manifest, MANIFEST).unwrap();
    let m = Manifest::load(manifest.to_str().unwrap()).unwrap();
    let runs = root.join("runs");
    let opts = PlanOptions {
        budget: "smoke".into(),
        out: runs.clone(),
        data_root: runs.join("data"),
        threads: 1,
        device: Default::default(),
        matmul: Default::default(),
        seeds: None,
    };
    let plan = pdt_repro::plan::plan(&m, &opts).unwrap();
    let mut dirs = Vec::new();
    for (r, ret) in plan.runs.iter().zip([8.0, 3.0]) {
        write_run(&r.dir, &r.config, &m.cells[r.cell].method, ret);
        dirs.push(r.dir.clone());
    }
    let registry = root.join("results");
    let added = registry::add(&AddOptions {
        runs: dirs,
        experiment: manifest.to_str().unwrap().into(),
        budget: "smoke".into(),
        data_root: None,
        registry: registry.clone(),
        provenance: ProvenanceFlags {
            commit: "abc1234".into(),
            device_name: "test CPU".into(),
            cpu: "test CPU".into(),
            libtorch: "test".into(),
            packing: "solo".into(),
            shared_with: 1,
            date: None,
            note: String::new(),
        },
    })
    .unwrap();
    assert_eq!(added.len(), 2);
    (manifest, registry)
}

const KEY: &str = "toy-main/prompt-dt/smoke/seed0";

#[test]
fn a_user_experiments_archived_runs_render_after_the_papers_with_their_claim() {
    let tmp = tempfile::tempdir().unwrap();
    let (_, registry) = archived(tmp.path());
    // The manifest is recorded from the registry's directory, where RESULTS.md lies.
    let prov = registry::provenance(&registry.join(KEY)).unwrap();
    assert_eq!(prov.manifest.as_deref(), Some("exp/manifest.toml"));
    assert_eq!(prov.experiment, "toy_exp");

    let md = render(&registry).unwrap_or_else(|e| panic!("render: {e}")).results_md;
    let head = "## Toy line: Prompt-DT against MT-ORL — user experiment `toy_exp`";
    let at = md.find(head).unwrap_or_else(|| panic!("no section {head:?}:\n{md}"));
    assert!(md.find("## What reproduces").is_some_and(|w| w < at), "after the paper's:\n{md}");
    let section = &md[at..];
    assert!(section.contains("[`exp/manifest.toml`](exp/manifest.toml)"), "{section}");
    assert!(section.contains("held-out goals.\n\n### `smoke` budget"), "{section}");
    // The last evaluation's mean return over g3 and g4: (8 + 7) / 2 and (3 + 2) / 2.
    assert!(
        section.contains("| Prompt-DT `toy-main/prompt-dt` | smoke | 1 (0) | 2 |"),
        "{section}"
    );
    // Normalised with the suite's returns (9 expert, 1 random): g3 87.5, g4 75.
    assert!(section.contains("| test CPU | 7.5 | 81.2 |"), "{section}");
    assert!(section.contains("| MT-ORL `toy-main/mt-orl` | smoke | 1 (0) | 2 | test CPU | 2.5 |"));
    // No paper value in a user's experiment: no paper columns.
    let header = section.lines().find(|l| l.starts_with("| cell |")).expect("a table header");
    assert!(header.ends_with("| ours, ratio of means |") && !header.contains("paper"), "{header}");
    // The claim, judged by the paper's rule: one seed a side is provisional.
    let claim =
        section.lines().find(|l| l.contains("Prompt-DT beats MT-ORL on the held-out goals"));
    let claim = claim.unwrap_or_else(|| panic!("no claim:\n{section}"));
    assert!(claim.contains("provisional (1 vs 1 seeds)"), "{claim}");
    assert!(section.contains("- **toy_exp (`smoke`)**:"), "{section}");

    // A checkout moved or cloned elsewhere (the runs record the suite file's absolute path, and
    // the run directories stay behind) renders the same.
    let moved = tmp.path().join("elsewhere");
    std::fs::create_dir(&moved).unwrap();
    for d in ["exp", "results"] {
        std::fs::rename(tmp.path().join(d), moved.join(d)).unwrap();
    }
    let again = render(&moved.join("results")).unwrap_or_else(|e| panic!("render: {e}"));
    assert!(again.results_md == md, "moved:\n{}", again.results_md);
}

#[test]
fn a_manifest_that_is_gone_or_renamed_and_an_archive_without_one_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let (manifest, registry) = archived(tmp.path());
    let moved = manifest.with_file_name("moved.toml");
    std::fs::rename(&manifest, &moved).unwrap();
    let e = render(&registry).err().unwrap().to_string();
    assert!(
        e.contains(&manifest.display().to_string())
            && e.contains("no such file")
            && e.contains(KEY)
            && e.contains("toy-main/mt-orl/smoke/seed0")
            && e.contains("nothing written"),
        "{e}"
    );
    // Now another experiment's manifest.
    std::fs::write(&manifest, MANIFEST.replace("name = \"toy_exp\"", "name = \"other\"")).unwrap();
    let e = render(&registry).err().unwrap().to_string();
    assert!(e.contains("now names experiment `other`") && e.contains(KEY), "{e}");
    std::fs::rename(&moved, &manifest).unwrap();
    assert!(render(&registry).is_ok());
    // An archive of a user experiment made before the manifest was recorded.
    let path = registry.join(KEY).join(registry::PROVENANCE_JSON);
    let text = std::fs::read_to_string(&path).unwrap();
    let line = "  \"manifest\": \"exp/manifest.toml\",\n";
    assert!(text.contains(line), "{text}");
    std::fs::write(&path, text.replace(line, "")).unwrap();
    let e = render(&registry).err().unwrap().to_string();
    assert!(
        e.contains(&format!("{KEY}: {}", path.display()))
            && e.contains("experiment `toy_exp` is no built-in one")
            && e.contains("names no manifest"),
        "{e}"
    );
}
