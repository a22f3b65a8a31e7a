//! `promptdt eval --adapt`: each evaluation-time adaptation (soft prompt tuning, the
//! Prompt-Tuning DT update, LoRA, full fine-tuning) end to end on a tiny trained point-robot run:
//! results in `eval_adapt_<kind>.json` with each task's adaptation log, on the reference
//! evaluation's tasks and episodes, and clear errors for bad settings. Full fine-tuning leaves the
//! run's checkpoints as they were and, with the weights as trained, is the reference rule.
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
    let checkpoints = files_in(&run.join("checkpoints"));

    for (name, extra) in [
        ("soft-prompt", vec!["--adapt-lr", "0.01"]),
        ("ptdt", vec!["--ptdt-candidates", "4"]),
        ("ptdt", vec!["--ptdt-candidates", "3", "--ptdt-score", "return"]),
        ("lora", vec!["--lora-rank", "2", "--lora-c-proj"]),
        ("full", vec!["--adapt-lr", "0.001"]),
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
    // Full fine-tuning changed the weights for each task's episodes only: the checkpoints on
    // disk are as they were.
    assert_eq!(files_in(&run.join("checkpoints")), checkpoints);
    // Reproducible: the same seed stream gives the same file.
    let again = |name: &str| {
        ok(&["eval", "--run", r, "--episodes", "2", "--adapt", name, "--adapt-steps", "2"]);
        let mut v = json(&run.join(format!("eval_adapt_{name}.json")));
        // wall times differ from run to run
        for l in v["adapt_log"].as_array_mut().unwrap() {
            l["seconds"] = serde_json::Value::Null;
        }
        v
    };
    assert_eq!(again("lora"), again("lora"));
    let full = again("full");
    assert_eq!(full, again("full"));
    // The weights moved: the demonstrations' probe loss is another after the tuning.
    for l in full["adapt_log"].as_array().unwrap() {
        assert_ne!(l["loss_before"], l["loss_after"], "{l}");
    }
    // With the weights as trained (a learning rate below every weight's float spacing: one step
    // moves none), full fine-tuning is the reference rule: the same tasks, prompts and reset
    // seeds, each task's episodes run alone. Bit for bit where a row alone and in a batch compute
    // alike (pdt_testkit::cpu::batch_invariant), else within `CROSS_CPU_RETURN_REL`.
    let args = ["--adapt", "full", "--adapt-steps", "1", "--adapt-lr", "1e-30"];
    ok(&[&["eval", "--run", r, "--episodes", "3"][..], &args[..]].concat());
    let got = json(&run.join("eval_adapt_full.json"));
    for (a, b) in got["tasks"].as_array().unwrap().iter().zip(tasks) {
        let (x, y) = (a["return_mean"].as_f64().unwrap(), b["return_mean"].as_f64().unwrap());
        if pdt_testkit::cpu::batch_invariant() {
            assert_eq!(x, y, "{a} vs {b}");
        } else {
            let rel = (x - y).abs() / y.abs().max(1e-12);
            assert!(rel <= pdt_testkit::cpu::CROSS_CPU_RETURN_REL, "{a} vs {b}");
        }
    }

    // Bad settings are refused with the value.
    let e = fails(&["eval", "--run", r, "--adapt", "lora", "--lora-rank", "0"]);
    assert!(e.contains("eval.adapt.lora.rank = 0"), "{e}");
    let e = fails(&["eval", "--run", r, "--adapt", "ptdt", "--ptdt-candidates", "1"]);
    assert!(e.contains("eval.adapt.ptdt.candidates = 1"), "{e}");
    let e = fails(&["eval", "--run", r, "--adapt", "soft-prompt", "--prompt-strategy", "bandit"]);
    assert!(e.contains("bandit") && e.contains("one prompt per task"), "{e}");
}

/// Every file directly in `dir`, by name, with its bytes.
fn files_in(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap())
        .filter(|e| e.path().is_file())
        .map(|e| (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap()))
        .collect()
}

#[test]
fn unknown_adaptations_are_refused_by_name() {
    let e = fails(&["eval", "--run", "/nonexistent", "--adapt", "adapter"]);
    assert!(e.contains("unknown adaptation `adapter`") && e.contains("soft-prompt"), "{e}");
}
