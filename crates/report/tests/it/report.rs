//! End-to-end tests: fake run directories with known numbers in a temp dir, then check every
//! output of `pdt_report::run`.

use std::fs;
use std::path::{Path, PathBuf};

use pdt_report::{run, ReportConfig, ReportError};
use serde_json::json;

type TestResult = Result<(), Box<dyn std::error::Error>>;

const ENV: &str = "point_robot";
/// (task name, task index); written out of index order on purpose.
const TASKS: [(&str, i64); 2] = [("point_robot-7", 7), ("point_robot-3", 3)];
const ITERS: [u64; 3] = [1, 2, 3];

/// Known returns. prompt-dt: task 3 = -10 + it + seed, task 7 = -20 + 2 it + seed.
fn prompt_dt_return(task_index: i64, it: u64, seed: u64) -> f64 {
    match task_index {
        3 => -10.0 + it as f64 + seed as f64,
        _ => -20.0 + 2.0 * it as f64 + seed as f64,
    }
}

/// mt-orl: task 3 = -30 + it + 2 seed, task 7 = -40 + it + 2 seed.
fn mt_orl_return(task_index: i64, it: u64, seed: u64) -> f64 {
    let base = if task_index == 3 { -30.0 } else { -40.0 };
    base + it as f64 + 2.0 * seed as f64
}

/// mt-orl seed 0 also has an eval_final.json, which must take precedence over eval.jsonl.
const MT_ORL_FINAL_SEED0: [(&str, i64, f64); 2] =
    [("point_robot-3", 3, -25.5), ("point_robot-7", 7, -35.5)];

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// Population std, the convention documented in docs/report.md.
fn pstd(v: &[f64]) -> f64 {
    let m = mean(v);
    (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len() as f64).sqrt()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-9
}

fn write_json(path: &Path, v: &serde_json::Value) -> std::io::Result<()> {
    fs::write(path, serde_json::to_string(v)? + "\n")
}

fn write_run_json(dir: &Path, method: &str, seed: u64) -> std::io::Result<()> {
    fs::create_dir_all(dir)?;
    write_json(
        &dir.join("run.json"),
        &json!({"name": format!("{method}-{ENV}-seed{seed}"), "method": method, "env": ENV,
                "seed": seed, "split": "default", "created": "2026-11-21T14:00:00Z",
                "promptdt_version": "0.1.0"}),
    )
}

fn write_eval_jsonl(dir: &Path, f: fn(i64, u64, u64) -> f64, seed: u64) -> std::io::Result<()> {
    let mut text = String::new();
    for it in ITERS {
        for (task, idx) in TASKS {
            // Train-split lines must be ignored by the report.
            for split in ["train", "test"] {
                let ret = if split == "test" { f(idx, it, seed) } else { 999.0 };
                let line = json!({"iteration": it, "step": it * 10, "split": split, "task": task,
                    "task_index": idx, "return_mean": ret, "return_std": 0.1, "length_mean": 20.0,
                    "episodes": 5, "target_return": 0.0});
                text.push_str(&line.to_string());
                text.push('\n');
            }
        }
    }
    fs::write(dir.join("eval.jsonl"), text)
}

fn write_metrics(dir: &Path) -> std::io::Result<()> {
    let mut text = String::new();
    for it in ITERS {
        let line = json!({"iteration": it, "step": it * 10, "train/action_loss": 1.0 / it as f64,
            "train/grad_norm": 0.3, "train/lr": 1e-4, "time/elapsed_s": it as f64 * 2.0});
        text.push_str(&line.to_string());
        text.push('\n');
    }
    fs::write(dir.join("metrics.jsonl"), text)
}

/// 3 seeds x 2 methods x 1 env under `root/<method>/seed<k>`.
fn make_runs(root: &Path) -> std::io::Result<()> {
    for seed in 0..3 {
        let dir = root.join("prompt-dt").join(format!("seed{seed}"));
        write_run_json(&dir, "prompt-dt", seed)?;
        write_eval_jsonl(&dir, prompt_dt_return, seed)?;
        write_metrics(&dir)?;

        let dir = root.join("mt-orl").join(format!("seed{seed}"));
        write_run_json(&dir, "mt-orl", seed)?;
        write_eval_jsonl(&dir, mt_orl_return, seed)?;
        write_metrics(&dir)?;
        if seed == 0 {
            let tasks: Vec<_> = MT_ORL_FINAL_SEED0
                .iter()
                .map(|(t, i, r)| {
                    json!({"task": t, "task_index": i, "return_mean": r,
                    "return_std": 0.2, "length_mean": 20.0, "episodes": 5, "returns": [r]})
                })
                .collect();
            write_json(
                &dir.join("eval_final.json"),
                &json!({"iteration": 3, "step": 30, "checkpoint": "checkpoints/step_30.safetensors",
                        "split": "test", "tasks": tasks, "mean_return": -30.5}),
            )?;
        }
    }
    Ok(())
}

fn config(runs: Vec<PathBuf>, out: &Path) -> ReportConfig {
    ReportConfig { runs, out_dir: out.to_path_buf(), title: Some("Test report".to_string()) }
}

/// Expected final per-seed values: [method][task or average] -> values over seeds 0..3.
fn expected_final(method: &str, task_index: Option<i64>) -> Vec<f64> {
    (0..3u64)
        .map(|seed| {
            let per_task = |idx: i64| -> f64 {
                if method == "mt-orl" && seed == 0 {
                    MT_ORL_FINAL_SEED0
                        .iter()
                        .find(|(_, i, _)| *i == idx)
                        .map_or(f64::NAN, |(_, _, r)| *r)
                } else if method == "mt-orl" {
                    mt_orl_return(idx, 3, seed)
                } else {
                    prompt_dt_return(idx, 3, seed)
                }
            };
            match task_index {
                Some(idx) => per_task(idx),
                None => (per_task(3) + per_task(7)) / 2.0,
            }
        })
        .collect()
}

/// Parses a CSV without quoted fields (none of the fixtures need quoting) into rows.
fn read_csv(path: &Path) -> Result<Vec<Vec<String>>, std::io::Error> {
    Ok(fs::read_to_string(path)?
        .lines()
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect())
}

#[test]
fn table_means_and_stds_match_known_numbers() -> TestResult {
    let tmp = tempfile::tempdir()?;
    make_runs(&tmp.path().join("runs"))?;
    let out = tmp.path().join("report");
    let summary = run(&config(vec![tmp.path().join("runs")], &out))?;
    assert_eq!(summary.runs_used, 6);
    assert_eq!(summary.runs_skipped, 0);
    assert!(summary.warnings.is_empty(), "{:?}", summary.warnings);

    let rows = read_csv(&out.join("table.csv"))?;
    assert_eq!(rows[0], ["env", "method", "task", "mean", "std", "n_seeds"]);
    // 2 methods x (2 tasks + average); paper order: prompt-dt before mt-orl; tasks by index.
    let keys: Vec<(String, String)> =
        rows[1..].iter().map(|r| (r[1].clone(), r[2].clone())).collect();
    let want_keys: Vec<(String, String)> = ["prompt-dt", "mt-orl"]
        .iter()
        .flat_map(|m| {
            ["point_robot-3", "point_robot-7", "average"]
                .iter()
                .map(move |t| (m.to_string(), t.to_string()))
        })
        .collect();
    assert_eq!(keys, want_keys);
    for r in &rows[1..] {
        assert_eq!(r[0], ENV);
        let idx = match r[2].as_str() {
            "point_robot-3" => Some(3),
            "point_robot-7" => Some(7),
            _ => None,
        };
        let vals = expected_final(&r[1], idx);
        let (m, s): (f64, f64) = (r[3].parse()?, r[4].parse()?);
        assert!(close(m, mean(&vals)), "{r:?}: mean {m} != {}", mean(&vals));
        assert!(close(s, pstd(&vals)), "{r:?}: std {s} != {}", pstd(&vals));
        assert_eq!(r[5], "3");
    }
    // Spot check against hand-computed numbers: prompt-dt average = -10.5 + seed at iteration 3.
    let pdt_avg = &rows[3];
    assert_eq!(pdt_avg[2], "average");
    assert!(close(pdt_avg[3].parse()?, -9.5));
    assert!(close(pdt_avg[4].parse()?, (2.0f64 / 3.0).sqrt()));

    // Markdown: same numbers with two decimals, in a table under the env heading.
    let md = fs::read_to_string(out.join("table.md"))?;
    assert_eq!(md, summary.markdown);
    assert!(md.starts_with("# Test report"));
    assert!(md.contains("## point_robot"));
    assert!(md.contains("| method | seeds | iteration | point_robot-3 | point_robot-7 | average |"));
    let avg_cell = format!("{:.2} ± {:.2}", -9.5, (2.0f64 / 3.0).sqrt());
    let pdt_line = md.lines().find(|l| l.starts_with("| prompt-dt |")).ok_or("no prompt-dt row")?;
    assert!(pdt_line.contains(&avg_cell), "{pdt_line}");
    // prompt-dt has the higher average, so it is the bold one.
    assert!(pdt_line.contains(&format!("**{avg_cell}**")), "{pdt_line}");
    let orl_vals = expected_final("mt-orl", Some(3));
    let orl_cell = format!("{:.2} ± {:.2}", mean(&orl_vals), pstd(&orl_vals));
    assert!(md.contains(&orl_cell), "{md}");
    Ok(())
}

#[test]
fn curves_csv_and_figures() -> TestResult {
    let tmp = tempfile::tempdir()?;
    make_runs(&tmp.path().join("runs"))?;
    let out = tmp.path().join("report");
    let summary = run(&config(vec![tmp.path().join("runs")], &out))?;

    let rows = read_csv(&out.join("curves.csv"))?;
    assert_eq!(rows[0], ["env", "method", "iteration", "mean", "std", "n_seeds"]);
    assert_eq!(rows.len(), 1 + 2 * ITERS.len());
    for r in &rows[1..] {
        let it: u64 = r[2].parse()?;
        let f = if r[1] == "prompt-dt" { prompt_dt_return } else { mt_orl_return };
        // Curves come from eval.jsonl only (eval_final.json is not a point on the curve).
        let per_seed: Vec<f64> = (0..3).map(|s| (f(3, it, s) + f(7, it, s)) / 2.0).collect();
        assert!(close(r[3].parse()?, mean(&per_seed)), "{r:?}");
        assert!(close(r[4].parse()?, pstd(&per_seed)), "{r:?}");
        assert_eq!(r[5], "3");
    }

    let png_path = out.join("curves_point_robot.png");
    let svg_path = out.join("curves_point_robot.svg");
    for p in [&png_path, &svg_path] {
        assert!(summary.files.contains(p), "{p:?} not in {:?}", summary.files);
    }
    let bytes = fs::read(&png_path)?;
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let mut reader = decoder.read_info()?;
    let mut buf = vec![0; reader.output_buffer_size().ok_or("no buffer size")?];
    let info = reader.next_frame(&mut buf)?;
    assert_eq!((info.width, info.height), (800, 500));
    let pixels = &buf[..info.buffer_size()];
    // A real plot: many distinct colours (text anti-aliasing, bands), and the first two
    // palette colours (prompt-dt, prompt-mt-bc slots are 0 and 1; mt-orl is slot 2) drawn.
    let distinct: std::collections::HashSet<&[u8]> = pixels.chunks(3).collect();
    assert!(distinct.len() > 50, "only {} colours", distinct.len());
    assert!(distinct.contains(&[31u8, 119, 180][..]), "prompt-dt line colour missing");
    assert!(distinct.contains(&[44u8, 160, 44][..]), "mt-orl line colour missing");

    let svg = fs::read_to_string(&svg_path)?;
    assert!(svg.starts_with("<svg"));
    // The text content of every <text> element (plotters puts it on its own line).
    let texts: Vec<&str> = svg
        .split("<text")
        .skip(1)
        .filter_map(|t| t.split_once('>').and_then(|(_, rest)| rest.split_once("</text>")))
        .map(|(content, _)| content.trim())
        .collect();
    for text in ["prompt-dt", "mt-orl", "Training iteration", "Average return on test tasks"] {
        assert!(texts.contains(&text), "SVG lacks text {text}: {texts:?}");
    }
    // Atomic writes leave no temporary files behind.
    let leftovers: Vec<_> = fs::read_dir(&out)?
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
    let mut names: Vec<String> = fs::read_dir(&out)?
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "curves.csv",
            "curves_point_robot.png",
            "curves_point_robot.svg",
            "runs.csv",
            "table.csv",
            "table.md"
        ]
    );
    Ok(())
}

#[test]
fn truncated_last_jsonl_line_is_skipped_with_warning() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    let victim = root.join("prompt-dt").join("seed1");
    // A run killed while appending: a partial line with no newline at the end.
    for file in ["eval.jsonl", "metrics.jsonl"] {
        let mut text = fs::read_to_string(victim.join(file))?;
        text.push_str(r#"{"iteration": 4, "step": 40, "split": "te"#);
        fs::write(victim.join(file), text)?;
    }
    let out = tmp.path().join("report");
    let summary = run(&config(vec![root], &out))?;
    assert_eq!(summary.warnings.len(), 2, "{:?}", summary.warnings);
    for (w, file) in summary.warnings.iter().zip(["eval.jsonl", "metrics.jsonl"]) {
        let line = if file == "eval.jsonl" { 13 } else { 4 };
        assert!(w.contains(&format!("{file}:{line}:")), "{w}");
        assert!(w.contains("truncated"), "{w}");
    }
    // Numbers unchanged: the partial line contributed nothing.
    let rows = read_csv(&out.join("table.csv"))?;
    let avg =
        rows.iter().find(|r| r[1] == "prompt-dt" && r[2] == "average").ok_or("no average row")?;
    assert!(close(avg[3].parse()?, -9.5));
    assert!(summary.markdown.contains("## Warnings"));
    Ok(())
}

#[test]
fn malformed_line_in_the_middle_is_an_error_with_file_and_line() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    let file = root.join("mt-orl").join("seed2").join("eval.jsonl");
    let text = fs::read_to_string(&file)?;
    let mut lines: Vec<&str> = text.lines().collect();
    lines[1] = "{\"iteration\": 1, \"split\": oops}";
    fs::write(&file, lines.join("\n") + "\n")?;
    let err = run(&config(vec![root], &tmp.path().join("out"))).err().ok_or("no error")?;
    let msg = err.to_string();
    assert!(matches!(err, ReportError::JsonLine { line: 2, .. }), "{msg}");
    assert!(msg.contains(&format!("{}:2:", file.display())), "{msg}");
    // A malformed *terminated* last line is corruption too, not a truncated write.
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    let last = lines.len();
    lines[last - 1] = "{\"iteration\": 3,".to_string();
    fs::write(&file, lines.join("\n") + "\n")?;
    let err = run(&config(vec![tmp.path().join("runs")], &tmp.path().join("out")))
        .err()
        .ok_or("no error")?;
    assert!(err.to_string().contains(&format!("eval.jsonl:{last}:")), "{err}");
    Ok(())
}

#[test]
fn malformed_run_json_names_the_file() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    let file = root.join("prompt-dt").join("seed0").join("run.json");
    fs::write(&file, r#"{"method": "prompt-dt", "env": "#)?;
    let err = run(&config(vec![root.clone()], &tmp.path().join("out"))).err().ok_or("no error")?;
    let msg = err.to_string();
    assert!(matches!(err, ReportError::Json { .. }), "{msg}");
    assert!(msg.contains(&file.display().to_string()), "{msg}");
    assert!(msg.contains("line 1"), "{msg}");

    // Well-formed but missing a required field: the message names the field.
    fs::write(&file, r#"{"env": "point_robot", "seed": 0}"#)?;
    let msg =
        run(&config(vec![root], &tmp.path().join("out"))).err().ok_or("no error")?.to_string();
    assert!(msg.contains(&file.display().to_string()) && msg.contains("method"), "{msg}");
    // Nothing was written when the report failed.
    assert!(!tmp.path().join("out").exists());
    Ok(())
}

#[test]
fn run_without_eval_data_is_reported() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    // A run that has started but not evaluated yet: run.json and metrics only.
    let empty = root.join("prompt-dt").join("seed3");
    write_run_json(&empty, "prompt-dt", 3)?;
    write_metrics(&empty)?;
    let out = tmp.path().join("report");
    let summary = run(&config(vec![root], &out))?;
    assert_eq!((summary.runs_used, summary.runs_skipped), (6, 1));
    let w = summary
        .warnings
        .iter()
        .find(|w| w.contains(&empty.display().to_string()))
        .ok_or("no warning names the run")?;
    assert!(w.contains("no test evaluation") && w.contains("eval.jsonl missing"), "{w}");
    assert!(w.contains("left out"), "{w}");
    // Seeds stay 3: the empty run does not dilute the mean.
    let rows = read_csv(&out.join("table.csv"))?;
    assert!(rows[1..].iter().all(|r| r[5] == "3"));
    let runs_csv = fs::read_to_string(out.join("runs.csv"))?;
    let line = runs_csv.lines().find(|l| l.contains("seed3")).ok_or("run missing from runs.csv")?;
    assert!(line.contains(",false,"), "{line}");
    assert_eq!(runs_csv.lines().count(), 1 + 7);

    // With no usable run at all, the report fails and says which run lacks what.
    let err =
        run(&config(vec![empty.clone()], &tmp.path().join("out2"))).err().ok_or("no error")?;
    assert!(matches!(err, ReportError::NoEvalData { .. }));
    let msg = err.to_string();
    assert!(
        msg.contains(&empty.display().to_string()) && msg.contains("eval.jsonl missing"),
        "{msg}"
    );
    Ok(())
}

#[test]
fn partial_evaluation_is_left_out_of_curve_and_table() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    // Seed 2 was killed during its 4th evaluation: only one of two test tasks was written.
    let file = root.join("prompt-dt").join("seed2").join("eval.jsonl");
    let mut text = fs::read_to_string(&file)?;
    text.push_str(
        &json!({"iteration": 4, "step": 40, "split": "test", "task": "point_robot-3",
                "task_index": 3, "return_mean": 100.0, "return_std": 0.1, "length_mean": 20.0,
                "episodes": 5, "target_return": 0.0})
        .to_string(),
    );
    text.push('\n');
    fs::write(&file, text)?;
    let out = tmp.path().join("report");
    let summary = run(&config(vec![root], &out))?;
    assert!(
        summary.warnings.iter().any(|w| w.contains("iteration(s) 4")),
        "{:?}",
        summary.warnings
    );
    let rows = read_csv(&out.join("curves.csv"))?;
    assert!(rows.iter().all(|r| r[2] != "4"));
    let table = read_csv(&out.join("table.csv"))?;
    let avg = table.iter().find(|r| r[1] == "prompt-dt" && r[2] == "average").ok_or("no row")?;
    assert!(close(avg[3].parse()?, -9.5));
    Ok(())
}

#[test]
fn discovery_dedups_and_rejects_bad_paths() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    let out = tmp.path().join("report");
    // The same run through its parent, itself and its run.json counts once.
    let one = root.join("prompt-dt").join("seed0");
    let summary = run(&config(vec![root.clone(), one.clone(), one.join("run.json")], &out))?;
    assert_eq!(summary.runs_used, 6);

    let missing = tmp.path().join("nope");
    let err = run(&config(vec![missing.clone()], &out)).err().ok_or("no error")?;
    assert!(err.to_string().contains(&missing.display().to_string()));

    let empty = tmp.path().join("empty");
    fs::create_dir_all(empty.join("sub"))?;
    let err = run(&config(vec![empty], &out)).err().ok_or("no error")?;
    assert!(matches!(err, ReportError::NoRunsFound { .. }), "{err}");

    let err = run(&config(vec![], &out)).err().ok_or("no error")?;
    assert!(matches!(err, ReportError::NoInput));
    Ok(())
}

#[test]
fn splits_and_envs_are_reported_separately() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    // The same env on the "ood" split must not be averaged with the default split.
    let ood = root.join("ood").join("prompt-dt-seed0");
    fs::create_dir_all(&ood)?;
    write_json(
        &ood.join("run.json"),
        &json!({"method": "prompt-dt", "env": ENV, "seed": 0, "split": "ood"}),
    )?;
    write_eval_jsonl(&ood, |_, it, _| it as f64, 0)?;
    let out = tmp.path().join("report");
    let summary = run(&config(vec![root], &out))?;
    assert!(summary.markdown.contains("## point_robot (ood)"));
    assert!(out.join("curves_point_robot_ood.png").is_file());
    let rows = read_csv(&out.join("table.csv"))?;
    let ood_avg = rows
        .iter()
        .find(|r| r[0] == "point_robot (ood)" && r[2] == "average")
        .ok_or("no ood row")?;
    assert!(close(ood_avg[3].parse()?, 3.0));
    assert_eq!(ood_avg[4], "0");
    assert_eq!(ood_avg[5], "1");
    Ok(())
}

#[test]
fn null_returns_are_left_out_and_counted() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let root = tmp.path().join("runs");
    make_runs(&root)?;
    // serde_json writes a NaN return as null; seed 2 diverged on task 7 at the last evaluation.
    let file = root.join("prompt-dt").join("seed2").join("eval.jsonl");
    let text = fs::read_to_string(&file)?;
    let mut lines: Vec<serde_json::Value> =
        text.lines().map(serde_json::from_str).collect::<Result<_, _>>()?;
    for l in &mut lines {
        if l["iteration"] == 3 && l["split"] == "test" && l["task_index"] == 7 {
            l["return_mean"] = serde_json::Value::Null;
        }
    }
    let text: String = lines.iter().map(|l| l.to_string() + "\n").collect();
    fs::write(&file, text)?;
    let out = tmp.path().join("report");
    let summary = run(&config(vec![root], &out))?;
    assert!(
        summary.warnings.iter().any(|w| w.contains("non-finite") && w.contains("point_robot-7@3")),
        "{:?}",
        summary.warnings
    );
    let rows = read_csv(&out.join("table.csv"))?;
    let get = |task: &str| rows.iter().find(|r| r[1] == "prompt-dt" && r[2] == task).cloned();
    let t7 = get("point_robot-7").ok_or("no task 7 row")?;
    let vals: Vec<f64> = (0..2).map(|s| prompt_dt_return(7, 3, s)).collect();
    assert_eq!(t7[5], "2");
    assert!(close(t7[3].parse()?, mean(&vals)));
    // Task 3 is unaffected; the diverged seed's average is undefined, so 2 seeds remain.
    assert_eq!(get("point_robot-3").ok_or("no task 3 row")?[5], "3");
    assert_eq!(get("average").ok_or("no average row")?[5], "2");
    assert!(summary.markdown.contains("(n=2)"));
    // On the curve, iteration 3 is averaged over the 2 finite seeds.
    let curve = read_csv(&out.join("curves.csv"))?;
    let p = curve.iter().find(|r| r[1] == "prompt-dt" && r[2] == "3").ok_or("no point")?;
    assert_eq!(p[5], "2");
    Ok(())
}

/// The run directories of testdata/rundir-v1, written before the schema crate (`split` for the
/// task split, no `loss_metric` in `run.json`): reported, each with its method's loss column
/// (a MACAW run's is `train/policy_outer_loss`, which it has always written).
#[test]
fn old_run_directories_are_reported_with_their_methods_loss() -> TestResult {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../testdata/rundir-v1/runs");
    let tmp = tempfile::tempdir()?;
    let out = tmp.path().join("report");
    let summary = run(&config(vec![fixture.clone()], &out))?;
    assert_eq!((summary.runs_used, summary.runs_skipped), (2, 0), "{:?}", summary.warnings);
    let rows = read_csv(&out.join("runs.csv"))?;
    let col = |name: &str| rows[0].iter().position(|c| c == name).ok_or(format!("no {name}"));
    let (method, metric, loss) = (col("method")?, col("loss_metric")?, col("last_loss")?);
    for (m, column) in [("macaw", "train/policy_outer_loss"), ("prompt-dt", "train/action_loss")] {
        let row = rows.iter().find(|r| r[method] == m).ok_or(format!("no {m} row"))?;
        assert_eq!(row[metric], column);
        let last = fs::read_to_string(fixture.join(m).join("metrics.jsonl"))?;
        let last: serde_json::Value =
            serde_json::from_str(last.lines().last().ok_or("no metrics")?)?;
        let want = last[column].as_f64().ok_or("no loss in metrics.jsonl")?;
        assert!(close(row[loss].parse()?, want), "{m}: {} vs {want}", row[loss]);
    }
    // The final values are those of eval_final.json (evaluated on "test", written as `split`).
    let runs = fs::read_to_string(out.join("runs.csv"))?;
    assert_eq!(runs.matches("eval_final.json").count(), 2, "{runs}");
    Ok(())
}
