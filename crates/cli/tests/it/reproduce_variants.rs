//! Evaluation variants of a trained cell through the real binary (docs/reproduce.md, "Variants"), on
//! a tiny point-robot experiment (seconds): a variant of an untrained cell is refused naming its
//! base run; after the training, each variant is one `promptdt eval` of its base run's weights in
//! its own directory (the base run untouched), reported like any cell, skipped once done, archived
//! by `results add` and reported from the registry alone.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{check_fails, check_ok, promptdt_in, s};
use std::path::Path;

/// The tiny manifest with two variants of its Prompt-DT cell.
fn manifest() -> String {
    let mut m = cli::tiny_manifest("variants", "Variants", "evaluation variants", 1);
    m.push_str(
        r#"
[[cells]]
env = "point_robot"
method = "prompt-dt"
variant = "best-return"
eval = { prompt = { strategy = "best-return" } }

[[cells]]
env = "point_robot"
method = "prompt-dt"
variant = "bandit"
eval = { episodes = 2, prompt = { strategy = "bandit", bandit = { rule = "ucb" } } }
"#,
    );
    m
}

#[derive(serde::Deserialize, Debug)]
struct CellJson {
    id: String,
    status: String,
    ours: Option<StatJson>,
}

#[derive(serde::Deserialize, Debug, Clone, Copy, PartialEq)]
struct StatJson {
    mean: f64,
}

#[derive(serde::Deserialize, Debug)]
struct ReportJson {
    cells: Vec<CellJson>,
}

fn report(out: &Path) -> ReportJson {
    let text = std::fs::read_to_string(out.join("reports/variants-smoke/report.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

#[test]
fn variants_evaluate_the_trained_runs_and_archive_like_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let m = root.join("variants.toml");
    std::fs::write(&m, manifest()).unwrap();
    let tree = root.join("tree");
    let base = ["reproduce", s(&m), "--budget", "smoke", "--out", s(&tree), "--jobs", "2"];
    let bandit = "point_robot/prompt-dt@bandit/smoke/seed0";

    // Before its base run is trained, a variant is refused, naming the base run.
    let only = [&base[..], &["--only", bandit]].concat();
    let err = check_fails(&only, promptdt_in(root, &only));
    assert!(err.contains(&format!("variant {bandit}")), "{err}");
    assert!(err.contains("base run point_robot/prompt-dt/smoke/seed0"), "{err}");
    assert!(err.contains("has not run yet"), "{err}");

    let out = check_ok(&base, promptdt_in(root, &base));
    assert!(out.contains("2 variant runs evaluated"), "{out}");
    let runs = tree.join("runs");
    let trained = runs.join("point_robot/prompt-dt/smoke/seed0");
    let v = runs.join(bandit);
    for f in ["variant.json", "eval.jsonl", "config.toml", "eval_prompt_bandit.json"] {
        assert!(v.join(f).is_file(), "{f}");
    }
    // The override is in the variant's configuration; the base run was not written to.
    let config = std::fs::read_to_string(v.join("config.toml")).unwrap();
    assert!(config.contains("rule = \"ucb\"") && config.contains("episodes = 2"), "{config}");
    let in_base: Vec<String> = std::fs::read_dir(&trained)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("eval_prompt_") || n == "variant.json")
        .collect();
    assert!(in_base.is_empty(), "{in_base:?}");
    let eval = std::fs::read_to_string(v.join("eval.jsonl")).unwrap();
    assert!(eval.contains("\"iteration\":2") && eval.contains("\"episodes\":2"), "{eval}");
    let r = report(&tree);
    let cell = |r: &ReportJson, id: &str| -> (String, Option<StatJson>) {
        let c = r.cells.iter().find(|c| c.id == id).unwrap_or_else(|| panic!("{id}: {r:?}"));
        (c.status.clone(), c.ours)
    };
    for id in ["point_robot/prompt-dt@best-return", "point_robot/prompt-dt@bandit"] {
        let (status, ours) = cell(&r, id);
        assert_eq!(status, "ran", "{id}");
        assert!(ours.is_some_and(|o| o.mean.is_finite()), "{id}");
    }

    // A second call finds everything done: 2 trained runs and 2 variants.
    let again = check_ok(&base, promptdt_in(root, &base));
    assert!(again.contains("4 runs already finished, 0 started, 0 resumed"), "{again}");
    assert!(!again.contains("variant runs evaluated"), "{again}");

    // Archived with the trained runs, then reported from the registry alone.
    let reg = root.join("reg");
    let mut add: Vec<String> = vec!["results".into(), "add".into()];
    for k in [
        "point_robot/prompt-dt/smoke/seed0",
        "point_robot/mt-orl/smoke/seed0",
        "point_robot/prompt-dt@best-return/smoke/seed0",
        bandit,
    ] {
        add.push(s(&runs.join(k)).into());
    }
    let data = tree.join("data");
    for x in ["--exp", s(&m), "--budget", "smoke", "--registry", s(&reg), "--data-root", s(&data)] {
        add.push(x.into());
    }
    for x in ["--commit", "abc1234", "--device-name", "cpu", "--cpu", "cpu", "--libtorch", "t"] {
        add.push(x.into());
    }
    check_ok(&add, promptdt_in(root, &add));
    let archived = reg.join(bandit);
    for f in ["variant.json", "eval_prompt_bandit.json", "provenance.json", "eval.jsonl"] {
        assert!(archived.join(f).is_file(), "{f}");
    }
    let fresh = root.join("fresh");
    let only_report = [
        "reproduce",
        s(&m),
        "--budget",
        "smoke",
        "--out",
        s(&fresh),
        "--registry",
        s(&reg),
        "--report-only",
    ];
    let out = check_ok(&only_report, promptdt_in(root, &only_report));
    assert!(out.contains("4 runs read from the registry"), "{out}");
    let (from_tree, from_registry) = (report(&tree), report(&fresh));
    for id in ["point_robot/prompt-dt@bandit", "point_robot/prompt-dt@best-return"] {
        assert_eq!(cell(&from_registry, id), cell(&from_tree, id), "{id}");
    }

    // A changed override is a changed configuration: the finished variant is not taken for it.
    std::fs::write(&m, manifest().replace("{ episodes = 2,", "{ episodes = 3,")).unwrap();
    let err = check_fails(&base, promptdt_in(root, &base));
    assert!(err.contains("eval.episodes (2 vs 3)"), "{err}");
}

/// A budget's `eval_repeats`: each variant is evaluated with `promptdt eval --repeats N`, its file
/// carries the N repeats, and the report shows the cell's evaluation noise (the spread over
/// repeats of the normalised score), apart from its seeds.
#[test]
fn variants_with_eval_repeats_report_their_evaluation_noise() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let m = root.join("variants.toml");
    let text = manifest()
        .replace("prompt_set_episodes = 2\n", "prompt_set_episodes = 2\neval_repeats = 3\n");
    assert!(text.contains("eval_repeats = 3"));
    std::fs::write(&m, text).unwrap();
    let tree = root.join("tree");
    let args = ["reproduce", s(&m), "--budget", "smoke", "--out", s(&tree), "--jobs", "2"];
    check_ok(&args, promptdt_in(root, &args));
    let v = tree.join("runs/point_robot/prompt-dt@best-return/smoke/seed0");
    let file: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(v.join("eval_prompt_best-return.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(file["repeats"]["task_returns"].as_array().unwrap().len(), 3, "{file}");
    let text = std::fs::read_to_string(tree.join("reports/variants-smoke/report.json")).unwrap();
    let rep: serde_json::Value = serde_json::from_str(&text).unwrap();
    let cell =
        |id: &str| rep["cells"].as_array().unwrap().iter().find(|c| c["id"] == id).unwrap().clone();
    let noise = &cell("point_robot/prompt-dt@best-return")["eval_noise"];
    assert_eq!(noise["repeats"], 3, "{noise}");
    assert!(noise["sd"].as_f64().is_some_and(|sd| sd.is_finite() && sd >= 0.0), "{noise}");
    // A trained cell's score is its training's evaluation: no repeats, no noise column value.
    assert!(cell("point_robot/prompt-dt")["eval_noise"].is_null());
    let md = std::fs::read_to_string(tree.join("reports/variants-smoke/report.md")).unwrap();
    assert!(md.contains("(3 repeats)"), "{md}");
}
