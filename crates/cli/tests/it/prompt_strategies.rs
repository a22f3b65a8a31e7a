//! `promptdt eval --prompt-strategy`: every strategy end to end on a tiny trained point-robot run,
//! its choices logged, and clear errors for an unknown name or a prompt that does not
//! fit.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{fails, ok, tiny_setup};
use std::path::Path;

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn every_strategy_evaluates_a_tiny_run_and_logs_its_choices() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    let r = run.to_str().unwrap();
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", r, "--quiet"]);
    let reference = ok(&["eval", "--run", r, "--episodes", "3"]);
    assert!(reference.contains("eval_final.json"), "{reference}");
    let final_eval = std::fs::read_to_string(run.join("eval_final.json")).unwrap();
    // The default, named: the same numbers into eval_final.json, unchanged.
    ok(&["eval", "--run", r, "--episodes", "3", "--prompt-strategy", "reference"]);
    assert_eq!(std::fs::read_to_string(run.join("eval_final.json")).unwrap(), final_eval);
    let tasks = json(&run.join("eval_final.json"))["tasks"].as_array().unwrap().len();

    for (name, extra) in [
        ("random-segment", vec![]),
        ("best-return", vec![]),
        ("nearest-start", vec!["--prompt-length", "3"]),
        ("bandit", vec!["--prompt-episodes", "2", "--bandit-rule", "ucb"]),
    ] {
        let mut args = vec!["eval", "--run", r, "--episodes", "3", "--prompt-strategy", name];
        args.extend(extra);
        let out = ok(&args);
        let file = run.join(format!("eval_prompt_{name}.json"));
        assert!(out.contains(&format!("eval_prompt_{name}.json")), "{out}");
        let v = json(&file);
        assert_eq!(v["prompt_strategy"]["strategy"], name);
        assert_eq!(v["tasks"].as_array().unwrap().len(), tasks, "{name}");
        for t in v["tasks"].as_array().unwrap() {
            assert_eq!(t["episodes"], 3, "{name}: {t}");
        }
        let picks = v["picks"].as_array().unwrap();
        let want = match name {
            // one prompt per task
            "random-segment" | "best-return" => tasks,
            // one per episode, chosen at its reset
            "nearest-start" => 3 * tasks,
            // one per task and round (1 episode per round)
            _ => 3 * tasks,
        };
        assert_eq!(picks.len(), want, "{name}");
        let j = if name == "bandit" { 2 } else { 1 };
        for p in picks {
            assert_eq!(p["segments"].as_array().unwrap().len(), j, "{name}: {p}");
            assert!(p["episode_return"].is_number(), "{name}: {p}");
        }
        if name == "bandit" {
            assert!(picks.iter().all(|p| p["round"].is_number() && p["explored"].is_boolean()));
        }
    }
    // eval_final.json stays the reference rule's
    assert_eq!(std::fs::read_to_string(run.join("eval_final.json")).unwrap(), final_eval);
    // A strategy is reproducible: the same seed stream gives the same file.
    let a = |_: ()| {
        ok(&["eval", "--run", r, "--episodes", "2", "--prompt-strategy", "random-segment"]);
        std::fs::read_to_string(run.join("eval_prompt_random-segment.json")).unwrap()
    };
    assert_eq!(a(()), a(()));
}

#[test]
fn unknown_strategies_and_prompts_that_do_not_fit_are_refused_by_name() {
    let e = fails(&["eval", "--run", "/nonexistent", "--prompt-strategy", "tail"]);
    assert!(e.contains("unknown prompt strategy `tail`") && e.contains("nearest-start"), "{e}");
    let e = fails(&["eval", "--run", "/nonexistent", "--bandit-rule", "thompson"]);
    assert!(e.contains("`thompson`"), "{e}");
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    let r = run.to_str().unwrap();
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", r, "--quiet"]);
    // 3 x (J*H + K) must fit the model's 1024 positions
    let e = fails(&["eval", "--run", r, "--prompt-length", "400"]);
    assert!(e.contains("1 x 400") && e.contains("1024"), "{e}");
    let e = fails(&["eval", "--run", r, "--prompt-strategy", "bandit", "--bandit-epsilon", "2"]);
    assert!(e.contains("bandit.epsilon") && e.contains('2'), "{e}");
}

#[test]
fn a_runs_eval_prompt_section_sets_its_evaluations_strategy() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let base = std::fs::read_to_string(&cfg).unwrap();
    // The default writes no [eval.prompt]: configuration files are what they were.
    let plain = tmp.path().join("plain");
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", plain.to_str().unwrap(), "--quiet"]);
    assert!(!std::fs::read_to_string(plain.join("config.toml")).unwrap().contains("prompt]"));
    let with = tmp.path().join("with.toml");
    let section = "\n[eval.prompt]\nstrategy = \"nearest-start\"\nlength = 3\n";
    std::fs::write(&with, format!("{base}{section}")).unwrap();
    let run = tmp.path().join("run");
    let r = run.to_str().unwrap();
    ok(&["train", "--config", with.to_str().unwrap(), "--out", r, "--quiet"]);
    let written = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(written.contains("[eval.prompt]") && written.contains("nearest-start"), "{written}");
    let out = ok(&["eval", "--run", r, "--episodes", "2"]);
    assert!(out.contains("eval_prompt_nearest-start.json"), "{out}");
    let v = json(&run.join("eval_prompt_nearest-start.json"));
    assert_eq!(v["prompt_strategy"]["length"], 3);
    // A method without a prompt refuses a strategy, naming both.
    let orl = tmp.path().join("orl.toml");
    std::fs::write(
        &orl,
        format!("{base}{section}").replace("[run]\n", "[run]\nmethod = \"mt-orl\"\n"),
    )
    .unwrap();
    let out_dir = tmp.path().join("orl");
    let e =
        fails(&["train", "--config", orl.to_str().unwrap(), "--out", out_dir.to_str().unwrap()]);
    assert!(e.contains("eval.prompt") && e.contains("mt-orl"), "{e}");
    // An unknown strategy name in the file is refused with the known ones.
    std::fs::write(&with, format!("{base}\n[eval.prompt]\nstrategy = \"tail\"\n")).unwrap();
    let e = fails(&[
        "train",
        "--config",
        with.to_str().unwrap(),
        "--out",
        tmp.path().join("x").to_str().unwrap(),
    ]);
    assert!(e.contains("tail") && e.contains("best-return"), "{e}");
}

/// Issue 56: a flag that acts only with another is refused by name; before, `--bandit-epsilon`
/// without the bandit was ignored (the evaluation ran the reference rule) and yet recorded in
/// `eval_prompt_reference.json`, and `--lora-rank` without `--adapt lora` was ignored.
#[test]
fn flags_that_act_only_with_another_are_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    let r = run.to_str().unwrap();
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", r, "--quiet"]);
    let cases: [(&[&str], &str); 6] = [
        (&["--bandit-epsilon", "0.3"], "--bandit-epsilon acts only with --prompt-strategy bandit"),
        (&["--prompt-strategy", "best-return", "--bandit-round", "2"], "--bandit-round acts only"),
        (
            &["--prompt-stride", "2"],
            "--prompt-stride acts only with --prompt-strategy nearest-start",
        ),
        (&["--lora-rank", "2"], "--lora-rank acts only with --adapt lora"),
        (
            &["--adapt", "soft-prompt", "--ptdt-sigma", "0.1"],
            "--ptdt-sigma acts only with --adapt ptdt",
        ),
        (
            &["--adapt", "ptdt", "--adapt-lr", "0.1"],
            "--adapt-lr acts only with --adapt soft-prompt, lora or full",
        ),
    ];
    for (flags, message) in cases {
        let mut args = vec!["eval", "--run", r, "--episodes", "1"];
        args.extend_from_slice(flags);
        let e = fails(&args);
        assert!(e.contains(message), "{flags:?}: {e}");
    }
    let written: Vec<_> = std::fs::read_dir(&run)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("eval_"))
        .collect();
    assert!(written.is_empty(), "nothing evaluated, nothing written: {written:?}");
    // With their strategy they act.
    ok(&[
        "eval",
        "--run",
        r,
        "--episodes",
        "1",
        "--prompt-strategy",
        "bandit",
        "--bandit-epsilon",
        "0.3",
    ]);
}

/// `promptdt eval --repeats N`: repeat 0 is the evaluation without the flag (its fields byte for
/// byte), the others draw their own prompts and reset seeds, reproducibly from the run's seed;
/// N = 1 writes the file exactly as before.
#[test]
fn eval_repeats_are_reproducible_and_one_repeat_is_todays_file() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    let r = run.to_str().unwrap();
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", r, "--quiet"]);
    let file = |name: &str| std::fs::read_to_string(run.join(name)).unwrap();
    ok(&["eval", "--run", r, "--episodes", "2"]);
    let today = file("eval_final.json");
    ok(&["eval", "--run", r, "--episodes", "2", "--repeats", "1"]);
    assert_eq!(file("eval_final.json"), today, "--repeats 1 changed eval_final.json");
    assert!(!today.contains("repeats"), "{today}");

    let out = ok(&["eval", "--run", r, "--episodes", "2", "--repeats", "5"]);
    assert!(out.contains("5 repeats"), "{out}");
    let five = file("eval_final.json");
    let (v, v0) = (
        json(&run.join("eval_final.json")),
        serde_json::from_str::<serde_json::Value>(&today).unwrap(),
    );
    // Repeat 0's fields are today's.
    for key in ["tasks", "mean_return", "iteration", "checkpoint"] {
        assert_eq!(v[key], v0[key], "{key}");
    }
    let rep = &v["repeats"];
    let rows = rep["task_returns"].as_array().unwrap();
    assert_eq!(rows.len(), 5);
    let tasks = v["tasks"].as_array().unwrap();
    for (t, task) in tasks.iter().enumerate() {
        assert_eq!(rows[0][t], task["return_mean"], "repeat 0 is the evaluation itself");
    }
    assert_eq!(rep["task_return_sd"].as_array().unwrap().len(), tasks.len());
    // Reproducible from the run's seed: the same file again.
    ok(&["eval", "--run", r, "--episodes", "2", "--repeats", "5"]);
    assert_eq!(file("eval_final.json"), five);
    // With a strategy, its own file carries the repeats.
    ok(&[
        "eval",
        "--run",
        r,
        "--episodes",
        "2",
        "--repeats",
        "3",
        "--prompt-strategy",
        "random-segment",
    ]);
    let s = json(&run.join("eval_prompt_random-segment.json"));
    let rows = s["repeats"]["task_returns"].as_array().unwrap();
    assert_eq!(rows.len(), 3);
    // Independent draws: a random window per repeat, so the repeats' returns differ.
    assert!(rows.iter().skip(1).any(|row| row != &rows[0]), "{s}");
    assert!(s["repeats"]["mean_return_sd"].as_f64().unwrap() > 0.0, "{s}");
    let e = fails(&["eval", "--run", r, "--repeats", "0"]);
    assert!(e.contains("--repeats") && e.contains("between 1 and 1000"), "{e}");
}
