//! End-to-end smoke tests: every subcommand of the real binary on a tiny budget, in a temp dir.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::golden;

use crate::cli;

use cli::{check_fails, check_ok, fails, losses, ok, promptdt_in, repo, tiny_setup};
use pdt_testkit::reference::official_prompts;
use std::process::Command;

#[test]
fn data_inspect_reads_all_official_prompt_files_as_table_and_json() {
    let Some(dir) = official_prompts() else { return };
    let d = dir.to_str().unwrap();
    let table = ok(&["data", "inspect", d]);
    assert!(table.contains("42 files, 210 trajectories, 42000 steps"), "{table}");
    let json: serde_json::Value =
        serde_json::from_str(&ok(&["data", "inspect", "--json", d])).unwrap();
    let files = json.as_array().unwrap();
    assert_eq!(files.len(), 42);
    // README figures: cheetah_dir-0 forward 630-687, cheetah_dir-1 backward 1129-1171
    let find =
        |stem: &str| files.iter().find(|f| f["path"].as_str().unwrap().contains(stem)).unwrap();
    let fwd = find("cheetah_dir-0-");
    assert!(
        fwd["return_min"].as_f64().unwrap() > 630.0 && fwd["return_max"].as_f64().unwrap() < 687.0
    );
    let bwd = find("cheetah_dir-1-");
    assert!(
        bwd["return_min"].as_f64().unwrap() > 1129.0
            && bwd["return_max"].as_f64().unwrap() < 1171.0
    );
}

#[test]
fn data_convert_then_inspect_the_native_files() {
    let Some(dir) = official_prompts() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let src = tmp.path().join("src");
    std::fs::create_dir(&src).unwrap();
    for f in ["cheetah_vel-2-prompt-expert.pkl", "cheetah_dir-1-prompt-expert.pkl"] {
        std::fs::copy(dir.join(f), src.join(f)).unwrap();
    }
    let dst = tmp.path().join("native");
    let out = ok(&["data", "convert", src.to_str().unwrap(), dst.to_str().unwrap()]);
    assert!(out.contains("converted 2 files"), "{out}");
    let native = ok(&["data", "inspect", dst.to_str().unwrap()]);
    let pickles = ok(&["data", "inspect", src.to_str().unwrap()]);
    assert!(
        native.contains("native") && native.contains("2 files, 10 trajectories, 2000 steps"),
        "{native}"
    );
    // same returns in both formats
    let returns = |t: &str| {
        t.lines()
            .filter(|l| l.contains("cheetah"))
            .map(|l| l.split_whitespace().rev().take(3).collect::<Vec<_>>().join(" "))
            .collect::<Vec<_>>()
    };
    assert_eq!(returns(&native), returns(&pickles));
}

/// Bit for bit against fixtures made on this CPU, within the measured cross-CPU bound otherwise
/// (`crates/train/tests/it/support/golden.rs`).
#[test]
fn model_forward_reproduces_the_pytorch_golden_predictions() {
    for set in golden::sets() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("preds.safetensors");
        let w = set.file("prompt_dt_state_dict.safetensors");
        let i = set.file("prompt_dt_inputs.safetensors");
        let msg = ok(&[
            "model",
            "forward",
            "--weights",
            w.to_str().unwrap(),
            "--inputs",
            i.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--threads",
            "1",
            "--n-head",
            "1",
        ]);
        assert!(msg.contains("[4, 20, 6]"), "{msg}");
        let ours = tch::Tensor::read_safetensors(&out).unwrap();
        let gold =
            tch::Tensor::read_safetensors(set.file("prompt_dt_expected.safetensors")).unwrap();
        let want = &gold.iter().find(|(n, _)| n == "eval.action_preds").unwrap().1;
        assert_eq!(ours.len(), 1);
        let d = (&ours[0].1 - want).abs().max().double_value(&[]);
        let allowed = if set.bitwise { 0.0 } else { golden::bounds::ACTION_ABS };
        assert!(
            d <= allowed,
            "{}: model forward differs from PyTorch by {d:e} (allowed {allowed:e})",
            set.label
        );
    }
}

#[test]
fn model_forward_errors_name_the_file_and_tensor() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("p.safetensors");
    let w = repo("testdata/golden/prompt_dt_state_dict.safetensors");
    let missing = fails(&[
        "model",
        "forward",
        "--weights",
        "/nonexistent.safetensors",
        "--inputs",
        w.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(missing.contains("/nonexistent.safetensors"), "{missing}");
    // weights given as inputs: no `states`
    let wrong = fails(&[
        "model",
        "forward",
        "--weights",
        w.to_str().unwrap(),
        "--inputs",
        w.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--n-head",
        "1",
    ]);
    assert!(wrong.contains("`states` is missing"), "{wrong}");
    let garbage = tmp.path().join("garbage.safetensors");
    std::fs::write(&garbage, b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all").unwrap();
    let bad = fails(&[
        "model",
        "forward",
        "--weights",
        garbage.to_str().unwrap(),
        "--inputs",
        w.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(bad.contains("garbage.safetensors"), "{bad}");
    assert!(!out.exists(), "no output on failure");
}

#[test]
fn bench_runs_promptdt_alone_on_a_tiny_budget() {
    let tmp = tempfile::tempdir().unwrap();
    let out = ok(&[
        "bench",
        "--threads",
        "1",
        "--iters",
        "2",
        "--warmup",
        "0",
        "--cases",
        "train_b4,infer_b1",
        "--out",
        tmp.path().to_str().unwrap(),
    ]);
    assert!(out.contains("train_b4") && out.contains("not run"), "{out}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path().join("bench.json")).unwrap())
            .unwrap();
    assert_eq!(json["promptdt"]["results"].as_array().unwrap().len(), 2);
    assert!(fails(&["bench", "--cases", "nonsense"]).contains("unknown benchmark case"));
}

#[test]
fn demo_smoke_trains_and_the_loss_goes_down() {
    let out = ok(&["demo", "--smoke", "--device", "cpu"]);
    let losses: Vec<f64> = out
        .lines()
        .filter_map(|l| l.split("loss ").nth(1)?.split_whitespace().next()?.parse().ok())
        .collect();
    assert_eq!(losses.len(), 20, "{out}");
    assert!(losses[15..].iter().sum::<f64>() < losses[..5].iter().sum::<f64>() * 0.6, "{losses:?}");
}

#[test]
fn demo_runs_end_to_end_on_a_tiny_budget() {
    let tmp = tempfile::tempdir().unwrap();
    let out = ok(&[
        "demo",
        "--iterations",
        "2",
        "--out",
        tmp.path().to_str().unwrap(),
        "--device",
        "cpu",
    ]);
    assert!(
        out.contains("prompt-dt") && out.contains("mt-orl") && out.contains("demo finished"),
        "{out}"
    );
    for f in [
        "report/table.md",
        "report/curves_point_robot.png",
        "report/curves.csv",
        "prompt-dt-seed0/eval_final.json",
        "mt-orl-seed0/eval_final.json",
    ] {
        assert!(tmp.path().join(f).is_file(), "missing {f}");
    }
}

#[test]
fn collect_train_eval_report_on_a_tiny_budget() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    let out = ok(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(out.contains("held-out tasks after iteration 8"), "{out}");
    for f in [
        "run.json",
        "config.toml",
        "task_stats.json",
        "metrics.jsonl",
        "metrics.csv",
        "eval.jsonl",
        "eval.csv",
        "checkpoints/latest.json",
        "checkpoints/step_16.safetensors",
    ] {
        assert!(run.join(f).is_file(), "missing {f}");
    }
    assert_eq!(losses(&run).len(), 8);
    let ev = ok(&["eval", "--run", run.to_str().unwrap(), "--episodes", "3"]);
    assert!(ev.contains("point_robot-34") && ev.contains("average (test)"), "{ev}");
    let fin: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval_final.json")).unwrap())
            .unwrap();
    assert_eq!(fin["tasks"].as_array().unwrap().len(), 5);
    assert_eq!(fin["tasks"][0]["episodes"], 3);
    let rep = tmp.path().join("rep");
    let table = ok(&["report", run.to_str().unwrap(), "--out", rep.to_str().unwrap()]);
    assert!(table.contains("prompt-dt"), "{table}");
    assert!(rep.join("curves_point_robot.png").is_file() && rep.join("table.csv").is_file());
    let err = fails(&["train", "--config", cfg.to_str().unwrap(), "--out", run.to_str().unwrap()]);
    assert!(err.contains("--resume"), "{err}");
}

#[test]
fn train_killed_with_sigkill_resumes_to_the_same_losses() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let text = std::fs::read_to_string(&cfg).unwrap().replace("iterations = 8", "iterations = 40");
    std::fs::write(&cfg, text).unwrap();
    let (full, cut) = (tmp.path().join("full"), tmp.path().join("cut"));
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", full.to_str().unwrap(), "--quiet"]);
    let mut child = Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args([
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--out",
            cut.to_str().unwrap(),
            "--quiet",
        ])
        .spawn()
        .unwrap();
    // Kill it once it has checkpointed at least once but before it finishes.
    let latest = cut.join("checkpoints/latest.json");
    let t0 = std::time::Instant::now();
    while !latest.exists() && t0.elapsed().as_secs() < 60 {
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let before = losses(&cut).len();
    assert!(before < 40, "the run finished before it could be killed");
    ok(&["train", "--resume", cut.to_str().unwrap(), "--quiet"]);
    assert_eq!(losses(&full), losses(&cut), "killed after {before} iterations");
}

#[test]
fn bad_input_gives_clear_errors() {
    assert!(fails(&["collect", "--env", "half-moon"]).contains("unknown environment `half-moon`"));
    assert!(fails(&["train", "--config", "/nonexistent.toml"]).contains("/nonexistent.toml"));
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tmp.path().join("bad.toml");
    std::fs::write(&cfg, "[train]\niteratons = 3\n").unwrap();
    assert!(fails(&["train", "--config", cfg.to_str().unwrap()]).contains("iteratons"));
    std::fs::write(&cfg, format!("[data]\ndir = {:?}\n", tmp.path().to_str().unwrap())).unwrap();
    let e = fails(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        tmp.path().join("r").to_str().unwrap(),
    ]);
    assert!(e.contains("point_robot-0-expert"), "names the missing file: {e}");
    assert!(fails(&["eval", "--run", tmp.path().to_str().unwrap()]).contains("config.toml"));
    std::fs::write(&cfg, "").unwrap();
    assert!(fails(&["train", "--config", cfg.to_str().unwrap(), "--method", "dt-xl"])
        .contains("--method dt-xl"));
}

#[test]
fn env_replay_matches_the_python_mujoco_fixture() {
    let fixture: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(repo("testdata/mujoco/replay-cheetah_vel.json")).unwrap(),
    )
    .unwrap();
    let case = &fixture["cases"][0];
    let tmp = tempfile::tempdir().unwrap();
    let (init, actions, out) = (
        tmp.path().join("init.json"),
        tmp.path().join("actions.json"),
        tmp.path().join("out.json"),
    );
    std::fs::write(
        &init,
        serde_json::json!({"qpos": case["init_qpos"], "qvel": case["init_qvel"]}).to_string(),
    )
    .unwrap();
    std::fs::write(&actions, case["actions"].to_string()).unwrap();
    let task = case["task"].to_string();
    let args = |task: &str| -> Vec<String> {
        let p = |f: &std::path::Path| f.to_str().unwrap().to_string();
        ["env", "replay", "--env", "cheetah_vel", "--task", task]
            .map(String::from)
            .into_iter()
            .chain([
                "--init".into(),
                p(&init),
                "--actions".into(),
                p(&actions),
                "--out".into(),
                p(&out),
            ])
            .collect()
    };
    let msg = ok(&args(&task));
    assert!(msg.contains("200 steps"), "{msg}");
    let got: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(got["observations"], case["expected"]["observations"]);
    assert_eq!(got["rewards"], case["expected"]["rewards"]);
    assert_eq!(got["truncated"], case["expected"]["truncated"]);
    // bad input: a wrong-length action is refused with a clear error
    std::fs::write(&actions, "[[0.1, 0.2]]").unwrap();
    let e = fails(&args("2"));
    assert!(e.contains("action has 2 values, expected 6"), "{e}");
    let e = fails(&args("40"));
    assert!(e.contains("unknown task 40"), "{e}");
}

#[test]
fn cheetah_vel_train_and_eval_on_the_official_prompt_files() {
    let Some(dir) = official_prompts() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tmp.path().join("cv.toml");
    let text = format!(
        "[env]\nname = \"cheetah_vel\"\n[data]\ndir = {:?}\ndataset_mode = \"prompt-expert\"\ntest_dataset_mode = \"prompt-expert\"\n\
         [sampler]\nbatch_size_per_task = 1\n[train]\niterations = 1\nsteps_per_iteration = 1\ntrain_eval_interval = 0\n[eval]\nepisodes = 2\n[run]\ndevice = \"cpu\"\n",
        dir.to_str().unwrap()
    );
    std::fs::write(&cfg, text).unwrap();
    let run = tmp.path().join("run");
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", run.to_str().unwrap(), "--quiet"]);
    let out = ok(&["eval", "--run", run.to_str().unwrap(), "--episodes", "2"]);
    for t in
        ["cheetah_vel-2", "cheetah_vel-7", "cheetah_vel-15", "cheetah_vel-23", "cheetah_vel-26"]
    {
        assert!(out.contains(t), "{out}");
    }
    let fin: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval_final.json")).unwrap())
            .unwrap();
    assert!(
        fin["tasks"].as_array().unwrap().iter().all(|t| t["length_mean"] == 200.0),
        "200-step episodes"
    );
}

#[test]
fn data_report_on_a_collected_point_robot_dataset() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let d = data.to_str().unwrap();
    ok(&["collect", "--env", "point_robot", "--episodes", "2", "--out", d]);
    // point_robot has no reference: the report works without --reference.
    let out = ok(&["data", "report", d]);
    assert!(out.contains("# Dataset returns: point_robot"), "{out}");
    assert!(out.contains("Reference: none given"), "{out}");
    assert!(out.contains("| task | expert | medium | random | prompt-expert |"), "{out}");
    assert!(out.contains("medium between random and expert"), "{out}");
    let report = data.join("report");
    for ext in ["csv", "md", "png", "svg"] {
        let f = report.join(format!("dataset_returns_point_robot.{ext}"));
        assert!(f.is_file() && out.contains(&format!("wrote {}", f.display())), "{out}");
    }
    let csv = std::fs::read_to_string(report.join("dataset_returns_point_robot.csv")).unwrap();
    assert_eq!(csv.lines().count(), 41, "40 tasks and a header");
    let png = std::fs::read(report.join("dataset_returns_point_robot.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"));
    // --out elsewhere; a directory with no data files is a clear error naming it.
    let other = tmp.path().join("other");
    ok(&["data", "report", d, "--out", other.to_str().unwrap()]);
    assert!(other.join("dataset_returns_point_robot.md").is_file());
    let e = fails(&["data", "report", other.to_str().unwrap()]);
    assert!(e.contains("no data files") && e.contains(other.to_str().unwrap()), "{e}");
}

/// Meta-World reach end to end on a tiny budget: scripted collection (success shown), the data
/// report's success column and bar, a replay of the expert's first actions, Prompt-DT trained for
/// two iterations, and an evaluation that reports the success rate beside the return.
#[test]
fn metaworld_reach_collect_report_replay_train_eval() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let d = data.to_str().unwrap();
    let out = ok(&[
        "collect",
        "--env",
        "metaworld_reach",
        "--episodes",
        "1",
        "--prompt-episodes",
        "1",
        "--modes",
        "expert",
        "--out",
        d,
    ]);
    // Every task of the paper's split (1-20), each with its success rate.
    assert!(out.contains("success") && out.contains("wrote 40 datasets"), "{out}");
    assert_eq!(out.matches("100.0%").count(), 20, "{out}");
    let e = fails(&["collect", "--env", "metaworld_reach", "--modes", "expert,best", "--out", d]);
    assert!(e.contains("unknown mode \"best\""), "{e}");
    let e = fails(&["collect", "--env", "metaworld_reach", "--tasks", "50", "--out", d]);
    assert!(e.contains("unknown task 50 of metaworld_reach"), "{e}");

    let rep = ok(&["data", "report", d]);
    assert!(rep.contains("(success 100 %)"), "{rep}");
    assert!(
        rep.contains("expert succeeds in every episode of every task**: met")
            || rep.contains("**met**: expert succeeds in every episode of every task"),
        "{rep}"
    );
    let csv =
        std::fs::read_to_string(data.join("report/dataset_returns_metaworld_reach.csv")).unwrap();
    assert!(csv.lines().next().unwrap().contains("expert_success_rate"), "{csv}");

    // Replay the recorded expert actions of task 6: the recorded rewards come back.
    let ds =
        pdt_data::native::read_task_dataset(&data.join("metaworld_reach-6-expert.safetensors"))
            .unwrap();
    let t = &ds.trajectories[0];
    let actions: Vec<Vec<f32>> = t.actions.chunks(4).take(60).map(<[f32]>::to_vec).collect();
    let acts = tmp.path().join("actions.json");
    std::fs::write(&acts, serde_json::to_string(&actions).unwrap()).unwrap();
    let res = tmp.path().join("replay.json");
    let a = acts.to_str().unwrap();
    ok(&[
        "env",
        "replay",
        "--env",
        "metaworld_reach",
        "--task",
        "6",
        "--actions",
        a,
        "--out",
        res.to_str().unwrap(),
    ]);
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&res).unwrap()).unwrap();
    let rewards: Vec<f32> =
        r["rewards"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
    assert_eq!(rewards, t.rewards[..60]);
    assert_eq!(r["success"].as_array().unwrap().len(), 60);
    let init = tmp.path().join("init.json");
    std::fs::write(&init, r#"{"qpos": [], "qvel": []}"#).unwrap();
    let e = fails(&[
        "env",
        "replay",
        "--env",
        "metaworld_reach",
        "--task",
        "6",
        "--actions",
        a,
        "--init",
        init.to_str().unwrap(),
        "--out",
        res.to_str().unwrap(),
    ]);
    assert!(e.contains("reset state"), "{e}");
    let e = fails(&[
        "env",
        "replay",
        "--env",
        "cheetah_vel",
        "--task",
        "6",
        "--actions",
        a,
        "--out",
        res.to_str().unwrap(),
    ]);
    assert!(e.contains("--init is required"), "{e}");
    let e = fails(&[
        "env",
        "replay",
        "--env",
        "nope",
        "--task",
        "6",
        "--actions",
        a,
        "--out",
        res.to_str().unwrap(),
    ]);
    assert!(e.contains("unknown environment `nope`"), "{e}");

    let cfg = tmp.path().join("reach.toml");
    let text = format!(
        "[env]\nname = \"metaworld_reach\"\n[data]\ndir = {d:?}\n[sampler]\nk = 4\n\
         batch_size_per_task = 1\n[model]\nhidden_size = 16\nn_layer = 1\nn_inner = 32\n\
         [train]\niterations = 2\nsteps_per_iteration = 2\ntest_eval_interval = 2\n\
         train_eval_interval = 0\nsave_interval = 2\n[eval]\nepisodes = 1\n\
         [run]\nthreads = 1\ndevice = \"cpu\"\n"
    );
    std::fs::write(&cfg, text).unwrap();
    let run = tmp.path().join("run");
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", run.to_str().unwrap(), "--quiet"]);
    let rows = std::fs::read_to_string(run.join("eval.jsonl")).unwrap();
    let first: serde_json::Value = serde_json::from_str(rows.lines().next().unwrap()).unwrap();
    let rate = first["success_rate"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&rate), "{first}");
    assert_eq!(first["length_mean"], 500.0);
    let ev = ok(&["eval", "--run", run.to_str().unwrap(), "--episodes", "1"]);
    assert!(ev.contains("success") && ev.contains("metaworld_reach-20"), "{ev}");
    assert!(ev.lines().filter(|l| l.trim_end().ends_with('%')).count() == 6, "{ev}");
}

#[test]
fn dial_collect_report_replay_train_eval() {
    use pdt_envs::Env;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let d = data.to_str().unwrap();
    let out = ok(&[
        "collect",
        "--env",
        "dial",
        "--episodes",
        "2",
        "--prompt-episodes",
        "1",
        "--modes",
        "expert,random",
        "--tasks",
        "1,2,3,4,5,8,6,7,9,0",
        "--out",
        d,
    ]);
    assert!(out.contains("success") && out.contains("wrote 40 datasets"), "{out}");
    assert_eq!(out.matches("100.0%").count(), 10, "{out}");
    let e = fails(&["collect", "--env", "dial", "--tasks", "10", "--out", d]);
    assert!(e.contains("unknown task 10 of dial"), "{e}");
    let e = fails(&["collect", "--env", "dial", "--action-noise", "0.1", "--out", d]);
    assert!(e.contains("--action-noise is for metaworld_reach"), "{e}");
    let rep = ok(&["data", "report", d]);
    assert!(rep.contains("(success 100 %)"), "{rep}");
    assert!(rep.contains("**met**: expert succeeds in every episode of every task"), "{rep}");

    // The noiseless expert's actions on digit 7, replayed: it reaches the digit at the same step.
    let mut env = pdt_envs::dial::Dial::new(7).unwrap();
    let mut expert = pdt_envs::dial::DialExpert::new(7).unwrap();
    let mut obs = env.reset(0);
    let mut actions: Vec<Vec<f32>> = Vec::new();
    loop {
        let a = expert.act(&obs);
        actions.push(a.to_vec());
        let s = env.step(&a).unwrap();
        obs = s.obs;
        if s.terminated || s.truncated {
            break;
        }
    }
    let n = actions.len();
    actions.extend(std::iter::repeat_n(vec![0.0; 9], 3));
    let acts = tmp.path().join("actions.json");
    std::fs::write(&acts, serde_json::to_string(&actions).unwrap()).unwrap();
    let (a, res) = (acts.to_str().unwrap(), tmp.path().join("replay.json"));
    let r = res.to_str().unwrap();
    let shown = ok(&["env", "replay", "--env", "dial", "--task", "7", "--actions", a, "--out", r]);
    assert!(shown.contains("return 1.000, terminated true"), "{shown}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&res).unwrap()).unwrap();
    assert_eq!(v["rewards"].as_array().unwrap().len(), n);
    assert_eq!(v["unused_actions"], 3);
    assert_eq!(v["success"].as_array().unwrap().last().unwrap(), true);
    // From a start pose (settled back first), and bad start poses named.
    let init = tmp.path().join("init.json");
    let q = pdt_envs::dial::targets().unwrap().init;
    std::fs::write(&init, format!("{{\"qpos\": {:?}}}", q.map(|x| x + 0.05))).unwrap();
    let i = init.to_str().unwrap();
    ok(&["env", "replay", "--env", "dial", "--task", "7", "--actions", a, "--init", i, "--out", r]);
    std::fs::write(&init, r#"{"qpos": [0, 0, 0]}"#).unwrap();
    let e = fails(&[
        "env",
        "replay",
        "--env",
        "dial",
        "--task",
        "7",
        "--actions",
        a,
        "--init",
        i,
        "--out",
        r,
    ]);
    assert!(e.contains("initial qpos has 3 values, expected 9"), "{e}");
    std::fs::write(&init, r#"{"qpos": [0, 0, 0, 0, 0, 0, 0, 0, 0], "qvel": []}"#).unwrap();
    let e = fails(&[
        "env",
        "replay",
        "--env",
        "dial",
        "--task",
        "7",
        "--actions",
        a,
        "--init",
        i,
        "--out",
        r,
    ]);
    assert!(e.contains("qvel"), "{e}");
    std::fs::write(&acts, "[[0, 0, 0, 0, 0, 0, 0, 0]]").unwrap();
    let e = fails(&["env", "replay", "--env", "dial", "--task", "7", "--actions", a, "--out", r]);
    assert!(e.contains("action has 8 values, expected 9"), "{e}");

    let cfg = tmp.path().join("dial.toml");
    let text = format!(
        "[env]\nname = \"dial\"\n[data]\ndir = {d:?}\n[sampler]\nk = 4\n\
         batch_size_per_task = 1\n[model]\nhidden_size = 16\nn_layer = 1\nn_inner = 32\n\
         [train]\niterations = 2\nsteps_per_iteration = 2\ntest_eval_interval = 2\n\
         train_eval_interval = 0\nsave_interval = 2\n[eval]\nepisodes = 1\n\
         [run]\nthreads = 1\ndevice = \"cpu\"\n"
    );
    std::fs::write(&cfg, text).unwrap();
    let run = tmp.path().join("run");
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", run.to_str().unwrap(), "--quiet"]);
    let rows = std::fs::read_to_string(run.join("eval.jsonl")).unwrap();
    // The four test digits (at iterations 1 and 2), each with its success rate.
    assert_eq!(rows.lines().count(), 8, "{rows}");
    for row in rows.lines() {
        let v: serde_json::Value = serde_json::from_str(row).unwrap();
        let rate = v["success_rate"].as_f64().unwrap();
        assert_eq!(rate, v["return_mean"].as_f64().unwrap(), "{v}");
    }
    let ev = ok(&["eval", "--run", run.to_str().unwrap(), "--episodes", "1"]);
    assert!(ev.contains("success") && ev.contains("dial-0"), "{ev}");
}

/// `reproduce`'s report normalises the paper's values with the reference experts' returns that the
/// manifest commits, so it is complete in a directory with no `../shared` beside it (it used to
/// read them from `../shared/data/official-prompts`, relative to the working directory, and leave
/// the column blank without). `--reference DIR` recomputes them from the release's files, giving
/// the same numbers, and a DIR that is not there is refused by name.
#[test]
fn reproduce_report_normalises_the_paper_without_the_reference_release() {
    let tmp = tempfile::tempdir().unwrap();
    let cwd = tmp.path().join("clone"); // nothing beside it: no ../shared
    std::fs::create_dir(&cwd).unwrap();
    let out = tmp.path().join("repro");
    let pretrained = repo("pretrained");
    let base = [
        "reproduce",
        "table1",
        "--budget",
        "smoke",
        "--out",
        out.to_str().unwrap(),
        "--pretrained-root",
        pretrained.to_str().unwrap(),
        "--jobs",
        "1",
        "--threads",
        "1",
    ];
    let run = [&base[..], &["--only", "cheetah_dir/prompt-dt-k1x2/smoke/seed0"]].concat();
    check_ok(&run, promptdt_in(&cwd, &run));
    let report_only = [&base[..], &["--report-only"]].concat();
    check_ok(&report_only, promptdt_in(&cwd, &report_only));
    let json = out.join("reports/table1-smoke/report.json");
    let cell = |json: &std::path::Path| -> serde_json::Value {
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
        let cells = r["cells"].as_array().unwrap();
        cells.iter().find(|c| c["id"] == "cheetah_dir/prompt-dt-k1x2").unwrap().clone()
    };
    let c = cell(&json);
    // 100 (paper - R_random) / (R_expert - R_random), test tasks 0 and 1 averaged: the experts
    // from table1.toml's [reference_experts.cheetah_dir], the random returns from the data's card.
    let manifest: toml::Value =
        toml::from_str(&std::fs::read_to_string(repo("experiments/table1.toml")).unwrap()).unwrap();
    let experts: Vec<f64> = manifest["reference_experts"]["cheetah_dir"]["returns"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_float().unwrap())
        .collect();
    let data = std::fs::read_dir(out.join("data"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.file_name().unwrap().to_string_lossy().starts_with("cheetah_dir"))
        .unwrap();
    let card: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(data.join("dataset.json")).unwrap()).unwrap();
    let random: Vec<f64> = card["tasks"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|t| t["files"].as_array().unwrap().iter())
        .filter(|f| f["mode"] == "random")
        .map(|f| f["returns"]["mean"].as_f64().unwrap())
        .collect();
    assert_eq!((experts.len(), random.len()), (2, 2), "{card}");
    let (e, r) = ((experts[0] + experts[1]) / 2.0, (random[0] + random[1]) / 2.0);
    let want = 100.0 * (926.46 - r) / (e - r);
    let got = c["paper_normalised"].as_f64().unwrap_or_else(|| panic!("no paper_normalised: {c}"));
    assert!((got - want).abs() < 1e-9, "{got} vs {want}");
    assert!((got - 101.8).abs() < 5.0, "Table 1's 926.46 is about 102 normalised: {got}");
    let md = std::fs::read_to_string(out.join("reports/table1-smoke/report.md")).unwrap();
    assert!(md.contains(&format!("{got:.1}")), "{md}");

    // --reference DIR: the release's files give the same numbers.
    if let Some(dir) = official_prompts() {
        let with = [&report_only[..], &["--reference", dir.to_str().unwrap()]].concat();
        check_ok(&with, promptdt_in(&cwd, &with));
        assert_eq!(cell(&json)["paper_normalised"], c["paper_normalised"]);
    }
    let missing = tmp.path().join("no-such-release");
    let bad = [&report_only[..], &["--reference", missing.to_str().unwrap()]].concat();
    let e = check_fails(&bad, promptdt_in(&cwd, &bad));
    assert!(e.contains("--reference") && e.contains("no-such-release"), "{e}");
}
