//! The typed files of a run directory: old names read, round trips, and errors that name the file.

use pdt_rundir::{
    EvalLine, FinalEval, Latest, MetricsLine, PackInfo, RunDir, RunDirError, RunInfo, RunStats,
    TaskResult, TrainState,
};
use std::collections::BTreeMap;
use std::fs;

type TestResult = Result<(), Box<dyn std::error::Error>>;

fn info(method: &str) -> RunInfo {
    RunInfo {
        name: format!("{method}-point_robot-seed0"),
        method: method.into(),
        env: "point_robot".into(),
        seed: 0,
        task_split: "default".into(),
        created: "2026-11-26T15:00:00Z".into(),
        promptdt_version: "0.1.0".into(),
        loss_metric: None,
        pack: None,
    }
}

fn task(index: usize, ret: f64) -> TaskResult {
    TaskResult {
        task: format!("point_robot-{index}"),
        task_index: index,
        return_mean: ret,
        return_std: 0.5,
        length_mean: 20.0,
        episodes: 2,
        returns: vec![ret - 0.5, ret + 0.5],
        success_rate: None,
    }
}

#[test]
fn run_json_reads_the_old_split_name_and_writes_the_new_one() -> TestResult {
    let old = r#"{"name": "a", "method": "prompt-dt", "env": "point_robot", "seed": 3,
        "split": "ood", "created": "2026-11-21T14:00:00Z", "promptdt_version": "0.1.0"}"#;
    let i: RunInfo = serde_json::from_str(old)?;
    assert_eq!((i.task_split.as_str(), i.seed, i.loss_metric.as_deref()), ("ood", 3, None));
    let text = serde_json::to_string(&i)?;
    assert!(text.contains("\"task_split\":\"ood\"") && !text.contains("\"split\""), "{text}");
    // An old run records no loss column: absent, not null.
    assert!(!text.contains("loss_metric"), "{text}");
    // A solo run records no pack; a packed run's record reads back.
    assert!(!text.contains("pack"), "{text}");
    let packed = RunInfo {
        pack: Some(PackInfo { size: 3, slot: 1, engine: "solo".into() }),
        ..info("mt-orl")
    };
    let back: RunInfo = serde_json::from_str(&serde_json::to_string(&packed)?)?;
    assert_eq!(back, packed);
    assert_eq!(serde_json::from_str::<RunInfo>(&text)?, i);
    Ok(())
}

#[test]
fn the_loss_column_comes_from_the_run_or_its_method() {
    assert_eq!(info("prompt-dt").loss_metric(), "train/action_loss");
    assert_eq!(info("mt-orl").loss_metric(), "train/action_loss");
    assert_eq!(info("macaw").loss_metric(), "train/policy_outer_loss");
    let mut i = info("macaw");
    i.loss_metric = Some("train/some_loss".into());
    assert_eq!(i.loss_metric(), "train/some_loss");
}

#[test]
fn eval_lines_read_the_old_split_name_and_null_returns() -> TestResult {
    let old = r#"{"iteration": 1, "step": 10, "split": "test", "task": "point_robot-3",
        "task_index": 3, "return_mean": null, "return_std": 0.5, "length_mean": 20.0,
        "episodes": 2, "target_return": 0.0}"#;
    let l: EvalLine = serde_json::from_str(old)?;
    assert!(l.is_test() && l.return_mean.is_nan() && l.success_rate.is_none());
    let text = serde_json::to_string(&l)?;
    assert!(text.contains("\"eval_on\":\"test\"") && !text.contains("success_rate"), "{text}");
    let back: EvalLine = serde_json::from_str(&text)?;
    assert!(back.return_mean.is_nan() && back.eval_on == "test");
    Ok(())
}

#[test]
fn final_eval_reads_the_old_split_name() -> TestResult {
    let old = r#"{"iteration": 3, "step": 30, "checkpoint": "checkpoints/step_30.safetensors",
        "split": "train", "tasks": [{"task": "point_robot-3", "task_index": 3, "return_mean": -2.5,
        "return_std": 0.1, "length_mean": 20.0, "episodes": 1, "returns": [null]}],
        "mean_return": -2.5}"#;
    let f: FinalEval = serde_json::from_str(old)?;
    assert_eq!(f.eval_on, "train");
    assert!(f.tasks[0].returns[0].is_nan() && f.adaptation.is_none());
    let text = serde_json::to_string(&f)?;
    assert!(text.contains("\"eval_on\":\"train\"") && !text.contains("\"split\""), "{text}");
    Ok(())
}

#[test]
fn metrics_lines_keep_the_methods_columns() -> TestResult {
    let line = r#"{"iteration": 2, "step": 20, "time/elapsed_s": 1.5,
        "train/policy_outer_loss": 0.25, "train/adv_coef": null}"#;
    let m: MetricsLine = serde_json::from_str(line)?;
    assert_eq!((m.iteration, m.step, m.elapsed_s), (2, 20, 1.5));
    assert_eq!(m.get(info("macaw").loss_metric()), Some(0.25));
    assert!(m.get("train/adv_coef").is_some_and(f64::is_nan));
    assert_eq!(m.get("train/action_loss"), None);
    assert_eq!(m.values.len(), 2);
    let text = serde_json::to_string(&m)?;
    let back: serde_json::Value = serde_json::from_str(&text)?;
    assert_eq!(back["train/policy_outer_loss"], 0.25);
    assert_eq!(back["time/elapsed_s"], 1.5);
    Ok(())
}

#[test]
fn a_run_directory_round_trips_through_its_writers_and_readers() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let dir = RunDir::at(tmp.path().join("run"));
    assert!(matches!(RunDir::open(dir.path()), Err(RunDirError::NotARunDir { .. })));
    dir.create_dir()?;
    let mut i = info("macaw");
    i.loss_metric = Some("train/policy_outer_loss".into());
    dir.write_info(&i)?;
    let dir = RunDir::open(dir.path())?;
    assert_eq!(dir.info()?, i);

    let config = pdt_rundir::config::TrainConfig::default();
    dir.write_config(&config)?;
    assert_eq!(dir.config()?, config);

    let stats = RunStats {
        obs_dim: 2,
        act_dim: 2,
        state_mean: vec![0.0, 1.0],
        state_std: vec![1.0, 2.0],
        rtg_scale: 1.0,
        target_return: 0.0,
        horizon: 20,
        train_tasks: vec![1, 2],
        test_tasks: vec![3],
        train_data_fingerprint: "a".into(),
        test_data_fingerprint: "b".into(),
    };
    dir.write_stats(&stats)?;
    assert_eq!(dir.stats()?, stats);
    stats.check()?;
    stats.check_same_as(&dir.stats()?)?;

    assert_eq!(dir.latest()?, None);
    fs::create_dir_all(dir.checkpoints_dir())?;
    let latest = Latest {
        step: 30,
        iteration: 3,
        model: Latest::model_name(30),
        state: Latest::state_name(30),
        keep: true,
    };
    dir.write_latest(&latest)?;
    assert_eq!(dir.latest()?, Some(latest));

    assert!(dir.eval_lines()?.is_none() && dir.metrics()?.is_none());
    let lines: Vec<EvalLine> = [task(3, -2.0), task(7, -4.0)]
        .iter()
        .map(|t| EvalLine::new(t, 3, 30, "test", 0.0))
        .collect();
    dir.append_eval_lines(&lines[..1])?;
    dir.append_eval_lines(&lines[1..])?;
    let read = dir.eval_lines()?.ok_or("no eval.jsonl")?;
    assert_eq!((read.rows, read.skipped), (lines, None));

    let metrics = MetricsLine {
        iteration: 3,
        step: 30,
        elapsed_s: 2.0,
        values: BTreeMap::from([("train/policy_outer_loss".to_string(), 0.5)]),
    };
    dir.append_metrics(std::slice::from_ref(&metrics))?;
    assert_eq!(dir.metrics()?.ok_or("no metrics.jsonl")?.rows, vec![metrics]);

    assert_eq!(dir.final_eval()?, None);
    let f = FinalEval {
        iteration: 3,
        step: 30,
        checkpoint: "checkpoints/step_30.safetensors".into(),
        eval_on: "test".into(),
        tasks: vec![task(3, -2.0)],
        mean_return: -2.0,
        adaptation: Some("1 steps on 256 transitions".into()),
        repeats: None,
    };
    dir.write_final_eval(&f)?;
    // One evaluation writes no `repeats` key: the file is as it was before repeats existed.
    assert!(!fs::read_to_string(dir.final_eval_path())?.contains("repeats"));
    assert_eq!(dir.final_eval()?, Some(f.clone()));
    // With repeats: every repeat's per-task returns, read back (a diverged one as NaN).
    let rows = vec![vec![-2.0, 4.0], vec![-4.0, 2.0], vec![-3.0, f64::NAN]];
    let two = pdt_rundir::EvalRepeats::of("s".into(), rows[..2].to_vec());
    assert_eq!(two.mean_returns, [1.0, -1.0]);
    // Sample SD (n - 1) of 1 and -1.
    assert!((two.mean_return_sd - 2f64.sqrt()).abs() < 1e-12, "{two:?}");
    assert!((two.task_return_sd[0] - 2f64.sqrt()).abs() < 1e-12, "{two:?}");
    let r = pdt_rundir::EvalRepeats::of("s".into(), rows);
    assert!((r.task_return_sd[0] - 1.0).abs() < 1e-12, "{r:?}");
    assert!(r.mean_return_sd.is_nan(), "{r:?}");
    let f = FinalEval { repeats: Some(r), ..f };
    dir.write_final_eval(&f)?;
    let back = dir.final_eval()?.ok_or("no eval_final.json")?;
    let (a, b) = (back.repeats.ok_or("no repeats")?, f.repeats.ok_or("no repeats")?);
    assert_eq!(a.task_returns[..2], b.task_returns[..2]);
    assert!(a.task_returns[2][1].is_nan() && a.mean_returns[2].is_nan());
    Ok(())
}

#[test]
fn truncated_and_malformed_files_give_errors_naming_the_file() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let dir = RunDir::at(tmp.path());
    fs::write(dir.info_path(), r#"{"name": "a", "method": "#)?;
    let e = RunDir::open(tmp.path())?.info().err().ok_or("no error")?;
    assert!(matches!(e, RunDirError::Json { .. }), "{e}");
    assert!(e.to_string().contains(&dir.info_path().display().to_string()), "{e}");

    // Well-formed but lacking a field: the message names the field.
    fs::write(dir.info_path(), r#"{"env": "point_robot", "seed": 0}"#)?;
    let e = dir.info().err().ok_or("no error")?.to_string();
    assert!(e.contains("run.json") && e.contains("method"), "{e}");

    fs::write(dir.stats_path(), "{\"obs_dim\": 2")?;
    let e = dir.stats().err().ok_or("no error")?.to_string();
    assert!(e.contains("task_stats.json"), "{e}");

    fs::write(dir.config_path(), "[train]\niterations = \"x\"\n")?;
    let e = dir.config().err().ok_or("no error")?.to_string();
    assert!(e.contains("config.toml"), "{e}");

    fs::create_dir_all(dir.checkpoints_dir())?;
    fs::write(
        dir.latest_path(),
        r#"{"step": 30, "iteration": 3, "model": "step_20.safetensors", "state": "s"}"#,
    )?;
    let e = dir.latest().err().ok_or("no error")?.to_string();
    assert!(e.contains("latest.json") && e.contains("step_20"), "{e}");

    // A truncated last line (no newline) is what a kill leaves: skipped and reported.
    let good = serde_json::to_string(&EvalLine::new(&task(3, -1.0), 1, 10, "test", 0.0))?;
    fs::write(dir.eval_path(), format!("{good}\n{{\"iteration\": 2,"))?;
    let read = dir.eval_lines()?.ok_or("no eval.jsonl")?;
    assert_eq!(read.rows.len(), 1);
    let skipped = read.skipped.ok_or("nothing skipped")?;
    assert_eq!(skipped.line, 2);
    assert!(skipped.to_string().contains("eval.jsonl:2: skipped a truncated last line"));
    // The same line with its newline, or in the middle, is an error naming the file and line.
    fs::write(dir.eval_path(), format!("{{\"iteration\": 2,\n{good}\n"))?;
    let e = dir.eval_lines().err().ok_or("no error")?;
    assert!(matches!(e, RunDirError::JsonLine { line: 1, .. }), "{e}");
    assert!(e.to_string().contains("eval.jsonl:1:"), "{e}");
    fs::write(dir.metrics_path(), "{\"iteration\": 1}\n")?;
    let e = dir.metrics().err().ok_or("no error")?.to_string();
    assert!(e.contains("metrics.jsonl:1:") && e.contains("step"), "{e}");
    Ok(())
}

#[test]
fn macaw_eval_lines_keep_their_adaptation_columns() -> TestResult {
    let line = r#"{"adapt_policy_steps":2,"adapt_value_steps":1,"episodes":1,"failed_episodes":0,
        "iteration":1,"length_mean":20.0,"return_mean":-36,"return_std":0.0,"split":"test",
        "step":2,"target_return":0.0,"task":"point_robot-2","task_index":2}"#;
    let l: EvalLine = serde_json::from_str(line)?;
    let a = l.adaptation.ok_or("no adaptation")?;
    assert_eq!((a.adapt_value_steps, a.adapt_policy_steps, a.failed_episodes), (1, 2, 0));
    assert_eq!(l.return_mean, -36.0);
    let text = serde_json::to_string(&l)?;
    assert!(text.contains("\"adapt_value_steps\":1"), "{text}");
    assert_eq!(serde_json::from_str::<EvalLine>(&text)?, l);
    let plain = EvalLine { adaptation: None, ..l };
    assert!(!serde_json::to_string(&plain)?.contains("adapt"));
    Ok(())
}

/// Run directories written by the code before this crate (testdata/rundir-v1, README there) read
/// through the typed files, with the old names.
#[test]
fn run_directories_written_before_the_schema_crate_are_read() -> TestResult {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../testdata/rundir-v1");
    let dirs = [
        ("prompt-dt", root.join("runs/prompt-dt"), true),
        ("macaw", root.join("runs/macaw"), true),
        ("prompt-dt", root.join("tree/runs/point_robot/prompt-dt/smoke/seed0"), false),
        ("macaw", root.join("tree/runs/point_robot/macaw/smoke/seed0"), false),
    ];
    for (method, path, evaluated) in dirs {
        let dir = RunDir::open(&path)?;
        let info = dir.info()?;
        assert_eq!((info.method.as_str(), info.task_split.as_str()), (method, "default"));
        assert_eq!(info.loss_metric, None);
        let config = dir.config()?;
        assert_eq!(config.run.method.name(), method);
        let stats = dir.stats()?;
        stats.check()?;
        assert!(!stats.train_data_fingerprint.is_empty());
        let latest = dir.latest()?.ok_or("no latest.json")?;
        assert_eq!((latest.iteration, latest.step, latest.keep), (2, 4, true));
        let metrics = dir.metrics()?.ok_or("no metrics.jsonl")?;
        assert_eq!(metrics.skipped, None);
        assert_eq!(metrics.rows.iter().map(|m| m.iteration).collect::<Vec<_>>(), vec![1, 2]);
        // The loss column named by the method is in every line.
        assert!(metrics.rows.iter().all(|m| m.get(info.loss_metric()).is_some_and(f64::is_finite)));
        let evals = dir.eval_lines()?.ok_or("no eval.jsonl")?;
        let test: Vec<&EvalLine> = evals.rows.iter().filter(|l| l.is_test()).collect();
        assert_eq!(test.len(), 2 * stats.test_tasks.len(), "{}", path.display());
        assert_eq!(test.iter().all(|l| l.adaptation.is_some()), method == "macaw");
        let fin = dir.final_eval()?;
        assert_eq!(fin.is_some(), evaluated, "{}", path.display());
        if let Some(f) = fin {
            assert_eq!((f.eval_on.as_str(), f.tasks.len()), ("test", stats.test_tasks.len()));
            assert_eq!(f.adaptation.is_some(), method == "macaw");
        }
    }
    Ok(())
}

/// `checkpoints/state_<N>.json` of the runs written before `TrainState` moved here (a Prompt-DT
/// run's, without `method`; a MACAW run's, with it) read and write back byte for byte, and one
/// without `keep` (older still) reads as kept.
#[test]
fn train_state_files_round_trip_byte_for_byte() -> TestResult {
    let runs =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../testdata/rundir-v1/runs");
    for (run, method) in [("prompt-dt", None), ("macaw", Some("macaw"))] {
        let path = runs.join(run).join("checkpoints/state_4.json");
        let state: TrainState = pdt_rundir::read_json(&path)?;
        assert_eq!(state.method.as_deref(), method, "{run}");
        assert_eq!((state.iteration, state.step, state.metrics_lines), (2, 4, 2), "{run}");
        assert_eq!(serde_json::to_string_pretty(&state)?, fs::read_to_string(&path)?, "{run}");
    }
    let old = r#"{"iteration": 1, "step": 2, "batch_rng_word_pos": "7", "adam_steps": {},
        "metrics_lines": 1, "eval_lines": 40}"#;
    assert!(serde_json::from_str::<TrainState>(old)?.keep);
    Ok(())
}
