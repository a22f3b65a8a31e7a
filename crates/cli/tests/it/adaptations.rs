//! `promptdt eval --adapt`: each evaluation-time adaptation (soft prompt tuning, the
//! Prompt-Tuning DT update, LoRA) end to end on a tiny trained point-robot run:
//! results in `eval_adapt_<kind>.json` with each task's adaptation log, on the reference
//! evaluation's tasks and episodes, and clear errors for bad settings.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{fails, ok, tiny_setup};
use std::path::Path;

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn every_adaptation_evaluates_a_tiny_run_and_logs_what_it_did() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    let r = run.to_str().unwrap();
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", r, "--quiet"]);
    ok(&["eval", "--run", r, "--episodes", "3"]);
    let final_eval = std::fs::read_to_string(run.join("eval_final.json")).unwrap();
    let reference = json(&run.join("eval_final.json"));
    let tasks = reference["tasks"].as_array().unwrap();

    for (name, extra) in [
        ("soft-prompt", vec!["--adapt-lr", "0.01"]),
        ("ptdt", vec!["--ptdt-candidates", "4"]),
        ("ptdt", vec!["--ptdt-candidates", "3", "--ptdt-score", "return"]),
        ("lora", vec!["--lora-rank", "2", "--lora-c-proj"]),
    ] {
        let mut args =
            vec!["eval", "--run", r, "--episodes", "3", "--adapt", name, "--adapt-steps", "3"];
        args.extend(extra.iter().copied());
        let out = ok(&args);
        assert!(out.contains(&format!("eval_adapt_{name}.json")), "{out}");
        let v = json(&run.join(format!("eval_adapt_{name}.json")));
        assert_eq!(v["adapt"]["kind"], name);
        assert_eq!(v["adapt"]["steps"], 3);
        let got = v["tasks"].as_array().unwrap();
        assert_eq!(got.len(), tasks.len(), "{name}");
        // The same held-out tasks, and the same number of episodes, as the reference's.
        for (a, b) in got.iter().zip(tasks) {
            assert_eq!(a["task"], b["task"], "{name}");
            assert_eq!(a["episodes"], 3, "{name}: {a}");
        }
        let log = v["adapt_log"].as_array().unwrap();
        assert_eq!(log.len(), tasks.len(), "{name}");
        for l in log {
            assert!(l["loss_before"].as_f64().unwrap().is_finite(), "{name}: {l}");
            assert!(l["loss_after"].as_f64().unwrap().is_finite(), "{name}: {l}");
            assert!(l["trainable"].as_u64().unwrap() > 0, "{name}: {l}");
            assert!(l["seconds"].as_f64().unwrap() >= 0.0, "{name}: {l}");
        }
        if extra.contains(&"--lora-c-proj") {
            assert_eq!(v["adapt"]["lora"]["rank"], 2);
            assert_eq!(v["adapt"]["lora"]["c_proj"], true);
        }
    }
    // eval_final.json stays the unadapted model's.
    assert_eq!(std::fs::read_to_string(run.join("eval_final.json")).unwrap(), final_eval);
    // Reproducible: the same seed stream gives the same file.
    let again = |_: ()| {
        ok(&["eval", "--run", r, "--episodes", "2", "--adapt", "lora", "--adapt-steps", "2"]);
        let mut v = json(&run.join("eval_adapt_lora.json"));
        // wall times differ from run to run
        for l in v["adapt_log"].as_array_mut().unwrap() {
            l["seconds"] = serde_json::Value::Null;
        }
        v
    };
    assert_eq!(again(()), again(()));

    // Bad settings are refused with the value.
    let e = fails(&["eval", "--run", r, "--adapt", "lora", "--lora-rank", "0"]);
    assert!(e.contains("eval.adapt.lora.rank = 0"), "{e}");
    let e = fails(&["eval", "--run", r, "--adapt", "ptdt", "--ptdt-candidates", "1"]);
    assert!(e.contains("eval.adapt.ptdt.candidates = 1"), "{e}");
    let e = fails(&["eval", "--run", r, "--adapt", "soft-prompt", "--prompt-strategy", "bandit"]);
    assert!(e.contains("bandit") && e.contains("one prompt per task"), "{e}");
}

#[test]
fn unknown_adaptations_are_refused_by_name() {
    let e = fails(&["eval", "--run", "/nonexistent", "--adapt", "adapter"]);
    assert!(e.contains("unknown adaptation `adapter`") && e.contains("soft-prompt"), "{e}");
}
