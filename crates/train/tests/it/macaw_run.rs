//! MACAW as a run (`run.method = "macaw"`): exact resumption, evaluation with another adaptation,
//! and clear errors for data that cannot serve and for checkpoints of another method.
#![allow(clippy::unwrap_used, clippy::result_large_err)] // test helpers: a failed unwrap is a failed test

use crate::runs;

use pdt_rundir::config::{Adaptation, Method, TestTime, TrainConfig};
use pdt_train::run::{evaluate_run, evaluate_run_as, EvalRequest};
use runs::{lines, run, tiny_data};
use std::path::Path;

fn config(data: &Path) -> TrainConfig {
    let mut c: TrainConfig = toml::from_str(
        r#"
        [run]
        method = "macaw"
        threads = 1
        device = "cpu"
        [env]
        name = "point_robot"
        [train]
        iterations = 6
        steps_per_iteration = 2
        test_eval_interval = 2
        train_eval_interval = 5
        save_interval = 2
        [eval]
        episodes = 2
        [macaw]
        width = 8
        buffer_skip = 1
        inner_batch = 8
        outer_batch = 8
        task_batch = 3
        adapt_batch = 4
        adapt_steps = 2
        "#,
    )
    .unwrap();
    c.data.dir = data.to_path_buf();
    c
}

#[test]
fn killed_and_resumed_macaw_run_equals_uninterrupted_run() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    let (full, cut) = (tmp.path().join("full"), tmp.path().join("cut"));
    assert!(run(Some(config(&data)), &full, false, None).unwrap().finished);
    let stopped = run(Some(config(&data)), &cut, false, Some(3)).unwrap();
    assert!(!stopped.finished);
    assert!(run(None, &cut, true, None).unwrap().finished);
    let (a, b) = (lines(&full.join("metrics.jsonl")), lines(&cut.join("metrics.jsonl")));
    assert_eq!(a.len(), 6);
    assert_eq!(a, b, "training losses differ after resume");
    assert!(a.iter().all(|r| r["train/policy_outer_loss"].as_f64().unwrap().is_finite()));
    let evals = lines(&full.join("eval.jsonl"));
    assert_eq!(evals, lines(&cut.join("eval.jsonl")), "evaluations differ");
    // 5 test goals at iterations 1, 3, 5, 6 and 35 training goals at 1 and 6
    assert_eq!(evals.len(), 4 * 5 + 2 * 35);
    assert!(evals.iter().all(|r| r["adapt_value_steps"].as_u64().unwrap() <= 2));
    let w = |d: &Path| std::fs::read(d.join("checkpoints/step_12.safetensors")).unwrap();
    assert!(w(&full) == w(&cut), "final weights differ");
    let m = |d: &Path| std::fs::read(d.join("checkpoints/state_12.safetensors")).unwrap();
    assert!(m(&full) == m(&cut), "final Adam moments differ");

    // Evaluation of the finished run, with its own and with the official adaptation.
    let own = evaluate_run(&full, Some(1), "test", None, None).unwrap();
    assert_eq!(own.tasks.len(), 5);
    assert_eq!(own.adaptation.as_deref(), Some("2 steps on 4 transitions"));
    let r = evaluate_run_as(&full, &with_macaw(1, 8)).unwrap().eval;
    assert_eq!(r.adaptation.as_deref(), Some("1 steps on 8 transitions"));
    // serving a MACAW run is refused with the reason
    let e = pdt_policy::Policy::load(&full, None, None).err().unwrap().to_string();
    assert!(e.contains("MACAW") && e.contains("promptdt eval"), "{e}");
}

#[test]
fn too_little_data_for_the_batches_is_refused_up_front_naming_the_task() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    let mut cfg = config(&data);
    // 4 episodes of 20 steps, every 7th kept: 12 rows per task, and a contiguous window of 12
    // needs 13 (the official start is randint(0, n - B)).
    cfg.macaw.buffer_skip = 7;
    cfg.macaw.inner_batch = 12;
    let dir = tmp.path().join("run");
    let e = run(Some(cfg), &dir, false, None).unwrap_err().to_string();
    assert!(e.contains("point_robot-") && e.contains("contiguous batch of 12"), "{e}");
    assert!(!dir.join("checkpoints").exists(), "nothing trained");
}

#[test]
fn a_checkpoint_of_another_method_is_a_clear_error() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    let mut m = config(&data);
    m.train.iterations = 2;
    let macaw = tmp.path().join("macaw");
    run(Some(m.clone()), &macaw, false, None).unwrap();
    let mut p: TrainConfig = m.clone();
    p.run.method = Method::MtOrl;
    p.model.hidden_size = 16;
    p.model.n_layer = 1;
    p.model.n_inner = 32;
    p.sampler.k = 4;
    p.sampler.batch_size_per_task = 1;
    let other = tmp.path().join("mt-orl");
    run(Some(p), &other, false, None).unwrap();
    // Swap the weights: each run's config now names the other method's checkpoint.
    let swap = |from: &Path, to: &Path| {
        std::fs::copy(
            from.join("checkpoints/step_4.safetensors"),
            to.join("checkpoints/step_4.safetensors"),
        )
        .unwrap();
    };
    let tmpw = tmp.path().join("w.safetensors");
    std::fs::copy(macaw.join("checkpoints/step_4.safetensors"), &tmpw).unwrap();
    swap(&other, &macaw);
    std::fs::copy(&tmpw, other.join("checkpoints/step_4.safetensors")).unwrap();
    let e = evaluate_run(&macaw, Some(1), "test", None, None).unwrap_err().to_string();
    assert!(e.contains("not MACAW weights"), "{e}");
    let e = evaluate_run(&other, Some(1), "test", None, None).unwrap_err().to_string();
    assert!(e.contains("step_4.safetensors"), "{e}");
    // a non-MACAW run refuses MACAW's adaptation, naming both
    let e = evaluate_run_as(&other, &with_macaw(1, 4)).unwrap_err().to_string();
    assert!(e.contains("macaw") && e.contains("mt-orl"), "{e}");
}

/// A one-episode evaluation with MACAW's adaptation at `steps` steps on `batch` transitions.
fn with_macaw(steps: usize, batch: usize) -> EvalRequest {
    let adaptation = Adaptation::Macaw { steps, batch };
    EvalRequest {
        episodes: Some(1),
        test_time: Some(TestTime::Adapt { from: Default::default(), adaptation }),
        ..Default::default()
    }
}

#[test]
fn a_non_finite_weight_or_moment_is_refused_by_name() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    let mut m = config(&data);
    m.train.iterations = 4;
    let dir = tmp.path().join("macaw");
    run(Some(m), &dir, false, Some(2)).unwrap(); // stopped after its checkpoint at step 4
    for file in ["step_4.safetensors", "state_4.safetensors"] {
        let path = dir.join("checkpoints").join(file);
        let good = std::fs::read(&path).unwrap();
        let mut tensors = tch::Tensor::read_safetensors(&path).unwrap();
        tensors.sort_by(|a, b| a.0.cmp(&b.0));
        let name = tensors[0].0.clone();
        let _ = tensors[0].1.view(-1).get(0).fill_(f64::NAN);
        tch::Tensor::write_safetensors(&tensors, &path).unwrap();
        let e = if file.starts_with("step") {
            evaluate_run(&dir, Some(1), "test", None, None).unwrap_err().to_string()
        } else {
            run(None, &dir, true, None).unwrap_err().to_string()
        };
        assert!(e.contains(file) && e.contains(&name) && e.contains("non-finite"), "{e}");
        std::fs::write(&path, good).unwrap();
    }
    run(None, &dir, true, None).unwrap();
}
