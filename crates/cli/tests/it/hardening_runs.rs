//! Training runs and evaluation under hostile input, through the real binary: each case
//! gets a clear error naming the setting, file or field, or is repaired, and loses nothing.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{edit_task0, fails, losses, ok, s, tiny_setup, train, variant};
use std::path::Path;

/// A message of ours: one line, single spaces (no line-continuation indentation leaked into it).
fn clean(e: String) -> String {
    assert!(!e.trim_end().contains('\n') && !e.contains("  "), "stray spaces or lines: {e:?}");
    e
}

/// Sets `key = value` (TOML value syntax) in `section` of a run's `config.toml`.
fn edit_run_config(run: &Path, section: &str, key: &str, value: &str) {
    let path = run.join("config.toml");
    let mut doc: toml::Table = std::fs::read_to_string(&path).unwrap().parse().unwrap();
    let v: toml::Table = format!("v = {value}").parse().unwrap();
    doc[section].as_table_mut().unwrap().insert(key.into(), v["v"].clone());
    std::fs::write(&path, toml::to_string(&doc).unwrap()).unwrap();
}

fn names_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn latest(run: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(run.join("checkpoints/latest.json")).unwrap())
        .unwrap()
}

/// Item 1: A target return whose return token the model cannot represent is refused by name before
/// anything is written (train) or evaluated (eval); an action that is not finite anyway stops the
/// evaluation naming the return token's settings.
#[test]
fn run_01_target_return_beyond_the_return_tokens_range_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let bad = variant(&cfg, "eval", "target_return", "1e30");
    let out = tmp.path().join("bad");
    let e = clean(fails(&["train", "--config", s(&bad), "--out", s(&out)]));
    assert!(
        e.contains("eval.target_return = 1e30") && e.contains("rtg_scale") && e.contains("1e6"),
        "{e}"
    );
    assert!(!out.join("config.toml").exists(), "nothing written: {e}");
    // a small rtg scale makes an ordinary target too large as well
    let bad = variant(&cfg, "sampler", "rtg_scale", "1e-30");
    let e = fails(&["train", "--config", s(&bad), "--out", s(&out)]);
    assert!(e.contains("sampler.rtg_scale = 1e-30"), "{e}");
    // a run whose configuration was edited afterwards: eval refuses it the same way
    let run = tmp.path().join("r");
    train(&cfg, &run, &["--iterations", "2"]);
    let good = std::fs::read_to_string(run.join("config.toml")).unwrap();
    edit_run_config(&run, "eval", "target_return", "1e30");
    let e = fails(&["eval", "--run", s(&run), "--episodes", "2"]);
    assert!(e.contains("eval.target_return = 1e30"), "{e}");
    std::fs::write(run.join("config.toml"), good).unwrap();
    // weights that are finite but absurd (every float scaled by 1e30): the actions are not
    // finite; the error says so and names the return token's settings among the causes
    let ck = run.join("checkpoints").join(latest(&run)["model"].as_str().unwrap());
    let tensors: Vec<(String, tch::Tensor)> = tch::Tensor::read_safetensors(&ck)
        .unwrap()
        .into_iter()
        .map(|(n, t)| {
            let t = if t.kind() == tch::Kind::Float && n.contains("c_attn") { t * 1e30 } else { t };
            (n, t)
        })
        .collect();
    tch::Tensor::write_safetensors(&tensors, &ck).unwrap();
    let e = clean(fails(&["eval", "--run", s(&run), "--episodes", "2"]));
    assert!(
        e.contains("not finite")
            && e.contains("eval.target_return")
            && e.contains("rtg_scale")
            && e.contains("weights"),
        "{e}"
    );
}

/// Item 2: State statistics that overflow or are absurd are refused, naming the task's file, the
/// field and the dimension.
#[test]
fn run_02_absurd_state_statistics_are_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let data = tmp.path().join("data");
    edit_task0(&data, |t| t.observations[1] = 3e38);
    let out = tmp.path().join("r");
    let e = clean(fails(&["train", "--config", s(&cfg), "--out", s(&out)]));
    assert!(
        e.contains("state_std[1]")
            && e.contains("point_robot-0-expert.safetensors")
            && e.contains("3e38")
            && e.contains("1e6"),
        "{e}"
    );
    assert!(!e.contains("00000000"), "compact numbers: {e}");
    assert!(!out.join("task_stats.json").exists(), "nothing written: {e}");
    // a run's recorded statistics are checked when read back, by name
    edit_task0(&data, |t| t.observations[1] = 0.5);
    train(&cfg, &out, &["--iterations", "1"]);
    let path = out.join("task_stats.json");
    let good = std::fs::read_to_string(&path).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
    v["state_std"][0] = 0.0.into();
    std::fs::write(&path, v.to_string()).unwrap();
    let e = clean(fails(&["eval", "--run", s(&out), "--episodes", "1"]));
    assert!(e.contains("task_stats.json") && e.contains("state_std[0] = 0"), "{e}");
    let e = fails(&["train", "--resume", s(&out), "--iterations", "2"]);
    assert!(e.contains("task_stats.json") && e.contains("state_std[0] = 0"), "{e}");
}

/// Item 3: A checkpoint's state file must account for every log line its iteration implies.
#[test]
fn run_03_state_file_claiming_fewer_log_lines_than_its_iteration_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("r");
    train(&cfg, &run, &[]);
    let state = run.join("checkpoints/state_16.json");
    let good = std::fs::read_to_string(&state).unwrap();
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let evals = std::fs::read_to_string(run.join("eval.jsonl")).unwrap();
    for (field, claim, expect) in [
        ("metrics_lines", "0", "iteration 8 implies 8"),
        ("metrics_lines", "5", "iteration 8 implies 8"),
        ("eval_lines", "0", "iteration 8 implies at least"),
    ] {
        let mut v: serde_json::Value = serde_json::from_str(&good).unwrap();
        v[field] = claim.parse::<u64>().unwrap().into();
        std::fs::write(&state, v.to_string()).unwrap();
        let e = clean(fails(&["train", "--resume", s(&run), "--iterations", "10"]));
        assert!(
            e.contains("state_16.json")
                && e.contains(&format!("{field} = {claim}"))
                && e.contains(expect),
            "{field} = {claim}: {e}"
        );
        // nothing was truncated
        assert_eq!(std::fs::read_to_string(run.join("metrics.jsonl")).unwrap(), metrics);
        assert_eq!(std::fs::read_to_string(run.join("eval.jsonl")).unwrap(), evals);
    }
    std::fs::write(&state, good).unwrap();
    ok(&["train", "--resume", s(&run), "--iterations", "10", "--quiet"]);
    assert_eq!(losses(&run).len(), 10);
}

/// Item 3b: The optimiser's moments file is checked like the weights: truncated, or holding a NaN,
/// the resume stops naming the file (and the tensor) in plain words, and the run resumes once the
/// file is whole again.
#[test]
fn run_03_a_broken_moments_file_is_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("r");
    train(&cfg, &run, &[]);
    let moments = run.join("checkpoints/state_16.safetensors");
    let good = std::fs::read(&moments).unwrap();
    std::fs::write(&moments, &good[..good.len() / 2]).unwrap();
    let e = clean(fails(&["train", "--resume", s(&run), "--iterations", "10"]));
    assert!(e.contains("state_16.safetensors") && e.contains("truncated"), "{e}");
    let mut tensors: Vec<(String, tch::Tensor)> = {
        std::fs::write(&moments, &good).unwrap();
        tch::Tensor::read_safetensors(&moments).unwrap()
    };
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    let (name, t) = &tensors[0];
    let name = name.clone();
    let _ = t.view(-1).get(0).fill_(f64::NAN);
    tch::Tensor::write_safetensors(&tensors, &moments).unwrap();
    let e = clean(fails(&["train", "--resume", s(&run), "--iterations", "10"]));
    assert!(
        e.contains("state_16.safetensors") && e.contains(&name) && e.contains("non-finite"),
        "{e}"
    );
    std::fs::write(&moments, &good).unwrap();
    ok(&["train", "--resume", s(&run), "--iterations", "10", "--quiet"]);
    assert_eq!(losses(&run).len(), 10);
}

/// Item 4a: Checkpoint files a killed run left behind (not referenced by `latest.json`) are removed
/// when the run next starts; the checkpoints in force are kept.
#[test]
fn run_04_orphaned_checkpoint_files_are_removed_on_the_next_start() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let (run, straight) = (tmp.path().join("r"), tmp.path().join("straight"));
    let frequent = variant(&cfg, "train", "resume_interval", "1");
    train(&frequent, &run, &[]);
    train(&cfg, &straight, &["--iterations", "10"]);
    let ck = run.join("checkpoints");
    let before = names_in(&ck);
    let copy = |from: &str, to: &str| std::fs::copy(ck.join(from), ck.join(to)).unwrap();
    // moments of an earlier checkpoint (killed after latest.json, before their removal)
    copy("state_16.safetensors", "state_12.safetensors");
    // a checkpoint written but never committed (killed before latest.json)
    copy("step_16.safetensors", "step_18.safetensors");
    copy("state_16.safetensors", "state_18.safetensors");
    copy("state_16.json", "state_18.json");
    // a resume point's files whose removal was cut short (not a kept checkpoint: keep = false)
    copy("step_16.safetensors", "step_14.safetensors");
    let mut point: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(ck.join("state_16.json")).unwrap()).unwrap();
    point["iteration"] = 7.into();
    point["step"] = 14.into();
    point["keep"] = false.into();
    std::fs::write(ck.join("state_14.json"), point.to_string()).unwrap();
    // a resume point's state file whose weights were already removed
    copy("state_16.json", "state_10.json");
    // the moments' temporary file of an older writer, killed mid-write
    copy("state_16.safetensors", ".state_18.safetensors.tmp");
    // the run is finished: resuming it trains nothing, but starts it (and tidies)
    ok(&["train", "--resume", s(&run), "--quiet"]);
    let after = names_in(&ck);
    for orphan in [
        "state_12.safetensors",
        "step_18.safetensors",
        "state_18.safetensors",
        "state_18.json",
        "step_14.safetensors",
        "state_14.json",
        "state_10.json",
        ".state_18.safetensors.tmp",
    ] {
        assert!(!after.contains(&orphan.to_string()), "{orphan} left behind: {after:?}");
    }
    // every kept checkpoint is still there
    for kept in before.iter().filter(|n| n.starts_with("step_")) {
        assert!(after.contains(kept), "{kept} removed: {after:?}");
    }
    ok(&["train", "--resume", s(&run), "--iterations", "10", "--quiet"]);
    assert_eq!(losses(&run), losses(&straight));
}

/// Item 4b: A run killed while its directory was being created resumes (what is missing is
/// recreated from the configuration and data), or says what happened and what to do.
#[test]
fn run_04_a_half_created_run_directory_resumes_or_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let (run, straight) = (tmp.path().join("r"), tmp.path().join("straight"));
    train(&cfg, &straight, &["--iterations", "3"]);
    // killed after config.toml, before task_stats.json: as if only those two were written
    train(&cfg, &run, &["--iterations", "3"]);
    for name in names_in(&run) {
        if !["run.json", "config.toml"].contains(&name.as_str()) {
            let p = run.join(&name);
            if p.is_dir() {
                std::fs::remove_dir_all(p).unwrap();
            } else {
                std::fs::remove_file(p).unwrap();
            }
        }
    }
    // eval says what happened rather than a raw "No such file or directory"
    let e = clean(fails(&["eval", "--run", s(&run)]));
    assert!(e.contains("task_stats.json") && e.contains("interrupted"), "{e}");
    ok(&["train", "--resume", s(&run), "--quiet"]);
    assert_eq!(losses(&run), losses(&straight));
    assert_eq!(
        std::fs::read_to_string(run.join("task_stats.json")).unwrap(),
        std::fs::read_to_string(straight.join("task_stats.json")).unwrap()
    );
    // killed before config.toml: named, with what to do
    let early = tmp.path().join("early");
    std::fs::create_dir(&early).unwrap();
    std::fs::copy(run.join("run.json"), early.join("run.json")).unwrap();
    let e = clean(fails(&["train", "--resume", s(&early)]));
    assert!(
        e.contains("interrupted while being created") && e.contains("delete it or rerun"),
        "{e}"
    );
    // a run with a checkpoint but no task_stats.json is not recreated from today's data
    std::fs::remove_file(straight.join("task_stats.json")).unwrap();
    let e = fails(&["train", "--resume", s(&straight), "--iterations", "4"]);
    assert!(e.contains("task_stats.json") && e.contains("checkpoint"), "{e}");
    assert!(!straight.join("task_stats.json").exists());
    // nor is a lost config.toml taken for an interrupted creation
    std::fs::remove_file(straight.join("config.toml")).unwrap();
    let e = fails(&["train", "--resume", s(&straight)]);
    assert!(e.contains("config.toml is missing") && e.contains("checkpoint"), "{e}");
}

/// Item 5: Messages print huge and tiny numbers compactly; a data mode that is empty or a path is
/// refused by name.
#[test]
fn run_05_messages_are_compact_and_data_modes_are_plain_names() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let out = tmp.path().join("r");
    for (section, key, value, expect) in [
        ("optim", "learning_rate", "1e300", "optim.learning_rate must be in (0, 1], got 1e300"),
        ("optim", "grad_clip_norm", "-1e300", "got -1e300"),
        ("optim", "learning_rate", "-1e-300", "got -1e-300"),
        ("data", "dataset_mode", "\"\"", "data.dataset_mode"),
        ("data", "dataset_mode", "\"../x\"", "data.dataset_mode"),
        ("data", "prompt_mode", "\"a/b\"", "data.prompt_mode"),
        ("data", "test_dataset_mode", "\"..\"", "data.test_dataset_mode"),
        ("data", "test_prompt_mode", "\"x\\\\y\"", "data.test_prompt_mode"),
    ] {
        let bad = variant(&cfg, section, key, value);
        let e = fails(&["train", "--config", s(&bad), "--out", s(&out)]);
        assert!(e.contains(expect), "{section}.{key} = {value}: {e}");
        assert!(!e.contains("0000000000"), "{section}.{key} = {value}: {e}");
        assert!(!out.join("config.toml").exists(), "{section}.{key}: nothing written");
    }
}

/// Item 4c: `train` killed with SIGKILL at several moments (while creating the directory, while
/// training, while checkpointing), then resumed each time: the run finishes with the losses and the
/// checkpoint files of a run never killed, and nothing unreferenced is left in `checkpoints/`.
#[test]
fn run_04_a_run_killed_again_and_again_ends_as_if_never_killed() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = variant(&tiny_setup(tmp.path()), "train", "resume_interval", "1");
    let (run, straight) = (tmp.path().join("r"), tmp.path().join("straight"));
    train(&cfg, &straight, &[]);
    for delay_ms in [5, 40, 120, 250, 400, 700, 1000] {
        // Until config.toml exists there is nothing to resume: start the run again.
        let args: Vec<&str> = if run.join("config.toml").is_file() {
            vec!["train", "--resume", s(&run), "--quiet"]
        } else {
            vec!["train", "--config", s(&cfg), "--out", s(&run), "--quiet"]
        };
        let mut child =
            std::process::Command::new(env!("CARGO_BIN_EXE_promptdt")).args(&args).spawn().unwrap();
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        let _ = child.kill(); // SIGKILL; it may have finished already
        child.wait().unwrap();
    }
    if run.join("config.toml").is_file() {
        ok(&["train", "--resume", s(&run), "--quiet"]);
    } else {
        train(&cfg, &run, &[]);
    }
    assert_eq!(losses(&run), losses(&straight));
    let files = |d: &Path| -> Vec<String> {
        names_in(&d.join("checkpoints")).into_iter().filter(|n| n != "latest.json").collect()
    };
    assert_eq!(files(&run), files(&straight));
}

/// A run trained with TF32 matmuls on a GPU (`run.matmul = "tf32"`, set here by hand: this machine
/// has none) is evaluated on the CPU in fp32, as the same run recorded with fp32 is, but is not
/// trained further there (refused by name, nothing changed); `--matmul` does not go with --resume.
#[test]
fn a_tf32_run_evaluates_on_the_cpu_and_is_not_trained_there() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let out = tmp.path().join("r");
    train(&cfg, &out, &["--iterations", "1"]);
    let eval = ["eval", "--run", s(&out), "--episodes", "1"];
    ok(&eval);
    let fp32 = std::fs::read(out.join("eval_final.json")).unwrap();
    edit_run_config(&out, "run", "matmul", "\"tf32\"");
    ok(&eval);
    assert_eq!(std::fs::read(out.join("eval_final.json")).unwrap(), fp32, "fp32 on the CPU");
    let before = names_in(&out);
    let e = clean(fails(&["train", "--resume", s(&out), "--iterations", "2"]));
    assert!(e.contains("matmul = tf32 needs a CUDA device, and the device is the CPU"), "{e}");
    assert_eq!(names_in(&out), before, "nothing written");
    assert_eq!(latest(&out)["iteration"], 1);
    let e = fails(&["train", "--resume", s(&out), "--matmul", "fp32"]);
    assert!(e.contains("--matmul") && e.contains("--resume"), "{e}");
}

/// `--matmul bf16` on a CPU without native bf16 is refused by name, with the flag to use instead
/// and the escape hatch, before anything is written; with the escape hatch (emulated bf16) the run
/// trains and records `matmul = "bf16"` in its config.toml. Where the CPU has native bf16 only the
/// second half applies.
#[test]
fn bf16_is_refused_without_native_bf16_and_recorded_when_it_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let out = tmp.path().join("r");
    let args = ["train", "--config", s(&cfg), "--out", s(&out), "--quiet", "--iterations", "1"];
    let mut args: Vec<&str> = args.to_vec();
    args.extend(["--matmul", "bf16"]);
    let run = |emulated: bool| {
        let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_promptdt"));
        c.args(&args).env_remove(pdt_torch::autocast::EMULATED_ENV);
        if emulated {
            c.env(pdt_torch::autocast::EMULATED_ENV, "1");
        }
        c.output().unwrap()
    };
    if pdt_torch::autocast::native_cpu().is_err() {
        let o = run(false);
        assert!(!o.status.success(), "bf16 without native bf16 trained");
        let e = String::from_utf8_lossy(&o.stderr);
        for part in ["matmul = bf16 needs", "--matmul fp32", "PROMPTDT_BF16_EMULATED=1"] {
            assert!(e.contains(part), "the refusal names `{part}`: {e}");
        }
        assert!(!out.exists(), "nothing written");
    }
    let o = run(true);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let toml = std::fs::read_to_string(out.join("config.toml")).unwrap();
    assert!(toml.contains("matmul = \"bf16\""), "{toml}");
}
