//! Bad input and faults, as a demanding user or an attacker would try them: each gets a clear
//! error naming the file, setting or step, and loses nothing (the cases numbered as in the
//! hardening review that listed them).
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{
    check_fails, check_ok, edit_task0, fails, losses, ok, promptdt_in, repo, s, tiny_data,
    tiny_setup, train, variant,
};
use std::path::Path;
use std::process::Command;

fn mkfifo(path: &Path) -> bool {
    Command::new("mkfifo").arg(path).status().is_ok_and(|s| s.success())
}

/// 1. A seed that TOML cannot hold is refused before anything is written.
#[test]
fn case_01_a_seed_beyond_toml_integers_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("r");
    let e =
        fails(&["train", "--config", s(&cfg), "--seed", "9223372036854775808", "--out", s(&run)]);
    assert!(e.contains("run.seed") && e.contains("9223372036854775807"), "{e}");
    assert!(!run.join("config.toml").exists());
    // the largest TOML integer is a valid seed, recorded exactly
    train(&cfg, &run, &["--seed", "9223372036854775807", "--iterations", "1"]);
    let text = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(text.contains("seed = 9223372036854775807"), "{text}");
}

/// 2. Two processes on one run directory: the second gets an error, the first is undisturbed.
#[test]
fn case_02_a_run_directory_has_one_owner() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = variant(&tiny_setup(tmp.path()), "train", "iterations", "100000");
    let run = tmp.path().join("r");
    // Killed on drop too, so a failing assertion leaves no 100000-iteration training behind.
    struct KillOnDrop(std::process::Child);
    impl Drop for KillOnDrop {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let mut first = KillOnDrop(
        Command::new(env!("CARGO_BIN_EXE_promptdt"))
            .args(["train", "--config", s(&cfg), "--out", s(&run), "--quiet"])
            .spawn()
            .unwrap(),
    );
    let metrics = run.join("metrics.jsonl");
    let t0 = std::time::Instant::now();
    while losses_len(&metrics) < 2 && t0.elapsed().as_secs() < 120 {
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    assert!(losses_len(&metrics) >= 2, "the first run did not start");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run), "--seed", "1"]);
    assert!(e.contains("in use by another promptdt process"), "{e}");
    let e = fails(&["train", "--resume", s(&run)]);
    assert!(e.contains("in use by another promptdt process"), "{e}");
    first.0.kill().unwrap();
    first.0.wait().unwrap();
    // the kernel released the lock with the process: the run resumes
    let text = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(text.contains("seed = 0"), "the second process wrote nothing: {text}");
    let latest: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(run.join("checkpoints/latest.json")).unwrap(),
    )
    .unwrap();
    let to = (latest["iteration"].as_u64().unwrap() + 2).to_string();
    ok(&["train", "--resume", s(&run), "--iterations", &to, "--quiet"]);
    assert_eq!(losses(&run).len().to_string(), to);
}

fn losses_len(p: &Path) -> usize {
    std::fs::read_to_string(p).map_or(0, |t| t.lines().count())
}

/// 3. `--resume` refuses what would make another run and extends `--iterations`.
#[test]
fn case_03_resume_refuses_other_runs_settings_and_extends_iterations() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let (run, straight) = (tmp.path().join("r"), tmp.path().join("straight"));
    train(&cfg, &run, &[]);
    for flags in [["--seed", "3"], ["--method", "mt-orl"], ["--config", s(&cfg)]] {
        let mut args = vec!["train", "--resume", s(&run)];
        args.extend_from_slice(&flags);
        let e = fails(&args);
        assert!(e.contains(flags[0]) && e.contains("cannot be used with"), "{e}");
    }
    let e = fails(&["train", "--resume", s(&run), "--iterations", "4"]);
    assert!(e.contains("already done 8 iterations"), "{e}");
    ok(&["train", "--resume", s(&run), "--iterations", "12", "--quiet"]);
    let text = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(text.contains("iterations = 12"), "{text}");
    // extending gives the losses of a run trained to 12 iterations at once
    train(&cfg, &straight, &["--iterations", "12"]);
    assert_eq!(losses(&run), losses(&straight));
}

/// 4. A run evaluates the same way from any directory and refuses data that changed.
#[test]
fn case_04_runs_record_their_data_and_refuse_changed_data() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    tiny_data(&t.join("data"));
    std::fs::write(t.join("rel.toml"), format!("{}\n[data]\ndir = \"data\"\n", cli::TINY)).unwrap();
    let args = ["train", "--config", "rel.toml", "--out", "r", "--quiet"];
    check_ok(&args, promptdt_in(t, &args));
    let run = t.join("r");
    let text = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(text.contains(&format!("dir = {:?}", s(&t.join("data")))), "absolute: {text}");
    let stats = std::fs::read_to_string(run.join("task_stats.json")).unwrap();
    assert!(stats.contains("\"train_data_fingerprint\": \"sha256:"), "{stats}");
    // from another directory
    let elsewhere = tempfile::tempdir().unwrap();
    let ev = ["eval", "--run", s(&run), "--episodes", "2"];
    let first = check_ok(&ev, promptdt_in(elsewhere.path(), &ev));
    // the data move (same content): --data finds them
    std::fs::rename(t.join("data"), t.join("moved")).unwrap();
    let e = fails(&ev);
    assert!(e.contains("data"), "{e}");
    let moved = t.join("moved");
    let mut with = ev.to_vec();
    with.extend_from_slice(&["--data", s(&moved)]);
    assert_eq!(ok(&with), first, "same data, same evaluation");
    // the data change (one reward of one file): refused, naming what changed
    edit_task0(&t.join("moved"), |tr| tr.rewards[0] += 0.5);
    let e = fails(&with);
    assert!(
        e.contains("task_stats.json") && e.contains("differ from what the run trained on"),
        "{e}"
    );
    let e =
        fails(&["train", "--resume", s(&run), "--iterations", "9", "--data", s(&t.join("moved"))]);
    assert!(e.contains("differ from what the run trained on"), "{e}");
}

/// 5. Settings outside their range are refused by name; a non-finite loss stops at its step.
#[test]
fn case_05_and_06_settings_are_validated_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    for (section, key, value, expect) in [
        ("optim", "grad_clip_norm", "-1.0", "optim.grad_clip_norm must be > 0"),
        ("optim", "eps", "-1.0", "optim.eps"),
        ("optim", "beta2", "2.0", "optim.beta2 must be in [0, 1)"),
        ("optim", "weight_decay", "nan", "optim.weight_decay"),
        ("optim", "learning_rate", "1e30", "optim.learning_rate must be in (0, 1]"),
        ("eval", "target_return", "nan", "eval.target_return must be finite"),
        ("eval", "target_return", "inf", "eval.target_return must be finite"),
        ("run", "threads", "2147483648", "run.threads must be at most 1024"),
        ("run", "threads", "100000", "run.threads must be at most 1024"),
        ("model", "hidden_size", "1000000000", "model.hidden_size must be between 1 and 16384"),
        ("model", "n_layer", "100000000", "model.n_layer"),
        ("model", "n_head", "3", "model.n_head = 3 must divide model.hidden_size = 16"),
        ("model", "max_ep_len", "5", "model.max_ep_len = 5 is below the longest episode"),
        ("eval", "episodes", "100000000", "eval.episodes must be between 1 and 10000"),
        ("eval", "finetune_batch", "0", "eval.finetune_batch"),
        ("train", "save_interval", "0", "train.save_interval"),
    ] {
        let bad = variant(&cfg, section, key, value);
        let out = tmp.path().join(format!("run-{section}-{key}"));
        let e =
            fails(&["train", "--config", s(&bad), "--out", s(&out), "--method", "mt-bc-finetune"]);
        assert!(e.contains(expect), "{section}.{key} = {value}: {e}");
        assert!(!out.join("config.toml").exists(), "{section}.{key}: nothing written");
    }
    // the CLI's own counts
    let e = fails(&["collect", "--env", "point-robot", "--episodes", "100000000"]);
    assert!(e.contains("between 1 and 100000"), "{e}");
    let e = fails(&["eval", "--run", "r", "--episodes", "100000000"]);
    assert!(e.contains("between 1 and 10000"), "{e}");
    let e = fails(&[
        "model",
        "forward",
        "--weights",
        "w",
        "--inputs",
        "i",
        "--out",
        "o",
        "--threads",
        "2147483648",
    ]);
    assert!(e.contains("between 1 and 1024"), "{e}");
}

/// 5. Data that would train on NaN: refused when read, or stopped at the first non-finite loss.
#[test]
fn case_05_extreme_data_is_refused_or_stops_at_the_step() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let data = tmp.path().join("data");
    edit_task0(&data, |t| t.rewards[0] = 3e38);
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&tmp.path().join("a"))]);
    assert!(e.contains("point_robot-0-expert.safetensors") && e.contains("return-to-go"), "{e}");
    edit_task0(&data, |t| {
        t.rewards[0] = 0.0;
        t.actions[0] = 1e30; // finite, but its squared error overflows f32
    });
    let run = tmp.path().join("b");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("training diverged at iteration 1, gradient step"), "{e}");
    assert!(e.contains("optim.learning_rate"), "names the likely causes: {e}");
}

/// 7. Devices, FIFOs and directories are refused instead of read forever or blocking on.
#[test]
fn case_07_devices_and_fifos_are_refused() {
    let e = fails(&["data", "inspect", "/dev/zero"]);
    assert!(e.contains("/dev/zero") && e.contains("a device"), "{e}");
    let tmp = tempfile::tempdir().unwrap();
    let fifo = tmp.path().join("fifo");
    if !mkfifo(&fifo) {
        return eprintln!("skipped the FIFO part: no mkfifo");
    }
    let w = repo("testdata/golden/prompt_dt_state_dict.safetensors");
    let i = repo("testdata/golden/prompt_dt_inputs.safetensors");
    let out = tmp.path().join("o.safetensors");
    // an RL agent directory whose card is a FIFO
    let agent = tmp.path().join("agent");
    std::fs::create_dir(&agent).unwrap();
    assert!(mkfifo(&agent.join("agent.json")));
    for args in [
        vec!["train", "--config", s(&fifo)],
        vec!["model", "forward", "--weights", s(&fifo), "--inputs", s(&i), "--out", s(&out)],
        vec![
            "model",
            "forward",
            "--weights",
            s(&w),
            "--inputs",
            s(&fifo),
            "--out",
            s(&out),
            "--n-head",
            "1",
        ],
        vec![
            "env",
            "replay",
            "--env",
            "cheetah_vel",
            "--task",
            "0",
            "--init",
            s(&fifo),
            "--actions",
            s(&fifo),
            "--out",
            s(&out),
        ],
        vec!["data", "inspect", s(&fifo)],
        vec![
            "collect",
            "--env",
            "cheetah_dir",
            "--from-pretrained",
            "--pretrained-dir",
            s(&agent),
            "--out",
            s(&out),
        ],
    ] {
        // A blocking read would hang here; the test harness's timeout would catch it.
        let e = fails(&args);
        assert!(e.contains("FIFO"), "{args:?}: {e}");
    }
}

/// 8. A checkpoint records its number of heads; weights that do not need `--n-head`.
#[test]
fn case_08_attention_heads_are_recorded_not_guessed() {
    let tmp = tempfile::tempdir().unwrap();
    let w = repo("testdata/golden/prompt_dt_state_dict.safetensors");
    let i = repo("testdata/golden/prompt_dt_inputs.safetensors");
    let out = tmp.path().join("o.safetensors");
    let e = fails(&["model", "forward", "--weights", s(&w), "--inputs", s(&i), "--out", s(&out)]);
    assert!(e.contains("--n-head") && e.contains("not recorded"), "{e}");
    let cfg = variant(&tiny_setup(tmp.path()), "model", "n_head", "2");
    let run = tmp.path().join("r");
    train(&cfg, &run, &["--iterations", "2"]);
    let ck = run.join("checkpoints/step_4.safetensors");
    let e = fails(&[
        "model",
        "forward",
        "--weights",
        s(&ck),
        "--inputs",
        s(&i),
        "--out",
        s(&out),
        "--n-head",
        "1",
    ]);
    assert!(e.contains("record n_head = 2"), "{e}");
    // recorded: no flag needed (the golden inputs have other dims, so the error is about them)
    let e = fails(&["model", "forward", "--weights", s(&ck), "--inputs", s(&i), "--out", s(&out)]);
    assert!(!e.contains("--n-head"), "{e}");
}

/// 9 and 12. Run-directory files are checked on resume; logs are repaired; temp files removed.
#[test]
fn case_09_and_12_run_directory_files_are_checked_and_repaired() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let (run, straight) = (tmp.path().join("r"), tmp.path().join("straight"));
    train(&cfg, &run, &[]);
    train(&cfg, &straight, &["--iterations", "12"]);
    let ck = run.join("checkpoints");
    // 12: temporary files of a killed writer are removed when the run starts again
    for stale in [ck.join(".step_18.safetensors.tmp.4242"), run.join(".metrics.csv.tmp-4242-0")] {
        std::fs::write(&stale, vec![0u8; 1000]).unwrap();
    }
    // 9: a deleted CSV is rebuilt from the JSON lines, with its header
    std::fs::remove_file(run.join("metrics.csv")).unwrap();
    ok(&["train", "--resume", s(&run), "--iterations", "12", "--quiet"]);
    assert!(!ck.join(".step_18.safetensors.tmp.4242").exists());
    assert!(!run.join(".metrics.csv.tmp-4242-0").exists());
    let csv = |d: &Path| -> Vec<String> {
        std::fs::read_to_string(d.join("metrics.csv"))
            .unwrap()
            .lines()
            .map(|l| {
                // drop the wall-clock column (third)
                let mut f: Vec<&str> = l.split(',').collect();
                f.remove(2);
                f.join(",")
            })
            .collect()
    };
    assert_eq!(csv(&run), csv(&straight));
    // latest.json pointing at another step's weights
    let latest = ck.join("latest.json");
    let good = std::fs::read_to_string(&latest).unwrap();
    std::fs::write(&latest, good.replace("step_24.safetensors", "step_4.safetensors")).unwrap();
    let e = fails(&["train", "--resume", s(&run), "--iterations", "14"]);
    assert!(e.contains("latest.json") && e.contains("expected `step_24.safetensors`"), "{e}");
    std::fs::write(&latest, good.replace("step_24.safetensors", "../../../etc/passwd")).unwrap();
    assert!(fails(&["eval", "--run", s(&run)]).contains("latest.json"));
    std::fs::write(&latest, &good).unwrap();
    // a truncated log cannot be repaired: refused with what is missing
    let m = run.join("metrics.jsonl");
    let text = std::fs::read_to_string(&m).unwrap();
    let short: String = text.lines().take(5).map(|l| format!("{l}\n")).collect();
    std::fs::write(&m, short).unwrap();
    let e = fails(&["train", "--resume", s(&run), "--iterations", "14"]);
    assert!(
        e.contains("metrics.jsonl") && e.contains("5 lines") && e.contains("recorded 12"),
        "{e}"
    );
    std::fs::write(&m, text).unwrap();
    ok(&["train", "--resume", s(&run), "--iterations", "14", "--quiet"]);
    assert_eq!(losses(&run).len(), 14);
}

/// 10. A dataset card that contradicts its files is refused by `train`, flagged by `data report`.
#[test]
fn case_10_a_contradicting_dataset_card_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let card = tmp.path().join("data/dataset.json");
    let good = std::fs::read_to_string(&card).unwrap();
    let edit = |from: &str, to: &str| {
        assert!(good.contains(from), "{from}");
        std::fs::write(&card, good.replacen(from, to, 1)).unwrap();
    };
    let run = tmp.path().join("r");
    edit("\"env\": \"point_robot\"", "\"env\": \"cheetah_dir\"");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("dataset.json") && e.contains("cheetah_dir"), "{e}");
    edit("\"obs_dim\": 2", "\"obs_dim\": 20");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("dataset.json") && e.contains("20/2"), "{e}");
    edit("\"point_robot-0-expert.safetensors\"", "\"../../../etc/passwd\"");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("not a plain file name"), "{e}");
    let report =
        ok(&["data", "report", s(&tmp.path().join("data")), "--out", s(&tmp.path().join("rep"))]);
    assert!(report.contains("not a plain file name"), "data report says so: {report}");
    std::fs::write(&card, &good).unwrap();
    train(&cfg, &run, &["--iterations", "1"]);
}

/// 11. `env replay` refuses states MuJoCo would reset.
#[test]
fn case_11_env_replay_refuses_states_mujoco_would_reset() {
    let tmp = tempfile::tempdir().unwrap();
    let (init, actions, out) =
        (tmp.path().join("init.json"), tmp.path().join("a.json"), tmp.path().join("o.json"));
    std::fs::write(&actions, "[[0.1, 0.1, 0.1, 0.1, 0.1, 0.1]]").unwrap();
    let replay = || {
        fails(&[
            "env",
            "replay",
            "--env",
            "cheetah_vel",
            "--task",
            "0",
            "--init",
            s(&init),
            "--actions",
            s(&actions),
            "--out",
            s(&out),
        ])
    };
    let mut qpos = ["0.0"; 9];
    qpos[1] = "1e308";
    std::fs::write(
        &init,
        format!("{{\"qpos\": [{}], \"qvel\": [{}]}}", qpos.join(","), ["0.0"; 9].join(",")),
    )
    .unwrap();
    let e = replay();
    assert!(e.contains("qpos[1]") && e.contains("would reset the simulation"), "{e}");
    assert!(!out.exists());
    // within the limit, but so fast that the first step diverges
    std::fs::write(
        &init,
        format!("{{\"qpos\": [{}], \"qvel\": [{}]}}", ["0.0"; 9].join(","), ["9e9"; 9].join(",")),
    )
    .unwrap();
    let e = replay();
    assert!(e.contains("diverged at step 0"), "{e}");
    assert!(!out.exists());
}

/// 13. Messages name the real cause.
#[test]
fn case_13_messages_name_the_real_cause() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("r");
    let missing = variant(&cfg, "data", "dir", &format!("{:?}", s(&tmp.path().join("nowhere"))));
    let e = fails(&["train", "--config", s(&missing), "--out", s(&run)]);
    assert!(e.contains("nowhere") && e.contains("No such file or directory"), "{e}");
    assert!(!e.contains("no expert data"), "{e}");
    let lp = tmp.path().join("loop");
    std::os::unix::fs::symlink(&lp, &lp).unwrap();
    let looping = variant(&cfg, "data", "dir", &format!("{:?}", s(&lp)));
    let e = fails(&["train", "--config", s(&looping), "--out", s(&run)]);
    assert!(e.contains("symbolic links"), "{e}");
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let e = fails(&["data", "inspect", s(&empty)]);
    assert!(e.contains("no .pkl or .safetensors files"), "{e}");
}

/// The same errors come out through the shared `check_fails` (no panic, an exit code).
#[test]
fn errors_are_exit_codes_not_crashes() {
    let args = ["train", "--resume", "/nonexistent-run"];
    let e = check_fails(&args, promptdt_in(Path::new("/"), &args));
    assert!(e.contains("no run to resume"), "{e}");
}

/// A checkpoint whose recorded heads contradict its run's `config.toml` is
/// refused where the run is acted with (`eval`) and where the file is run on its own (`model
/// forward`), naming both; before, each ran it with whichever number it read.
#[test]
fn round3_recorded_heads_must_be_the_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = variant(&tiny_setup(tmp.path()), "model", "n_head", "2");
    let run = tmp.path().join("r");
    train(&cfg, &run, &["--iterations", "2"]);
    let ck = run.join("checkpoints/step_4.safetensors");
    // The metadata is JSON inside the header's JSON: `\"n_head\":2`; the same length as `...4`, so
    // the header's length prefix stays right.
    let mut bytes = std::fs::read(&ck).unwrap();
    let (from, to) = (br#"\"n_head\":2"#, br#"\"n_head\":4"#);
    let at = bytes.windows(from.len()).position(|w| w == from).expect("recorded n_head = 2");
    bytes[at..at + from.len()].copy_from_slice(to);
    std::fs::write(&ck, &bytes).unwrap();
    let e = fails(&["eval", "--run", s(&run), "--episodes", "1"]);
    assert!(e.contains("step_4.safetensors"), "{e}");
    assert!(e.contains("record n_head = 4") && e.contains("n_head = 2"), "{e}");
    let (i, out) = (tmp.path().join("in.safetensors"), tmp.path().join("o.safetensors"));
    std::fs::copy(repo("testdata/golden/prompt_dt_inputs.safetensors"), &i).unwrap();
    let e = fails(&["model", "forward", "--weights", s(&ck), "--inputs", s(&i), "--out", s(&out)]);
    assert!(e.contains("the weights have n_head = 4") && e.contains("config.toml"), "{e}");
    assert!(e.contains("[model] n_head = 2"), "{e}");
    // Outside a run directory nothing says otherwise: the recorded 4 heads run (the golden inputs
    // have other dims, so the error is about them, not the heads).
    let alone = tmp.path().join("alone.safetensors");
    std::fs::copy(&ck, &alone).unwrap();
    let e =
        fails(&["model", "forward", "--weights", s(&alone), "--inputs", s(&i), "--out", s(&out)]);
    assert!(!e.contains("n_head"), "{e}");
}

/// A sample whose attention mask is all padding is refused by row, in the
/// history and in the prompt; before, it ran and returned actions that mean nothing.
#[test]
fn round3_an_all_zero_attention_mask_row_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let w = repo("testdata/golden/prompt_dt_state_dict.safetensors");
    let golden = std::fs::read(repo("testdata/golden/prompt_dt_inputs.safetensors")).unwrap();
    let n = u64::from_le_bytes(golden[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&golden[8..8 + n]).unwrap();
    let out = tmp.path().join("o.safetensors");
    for name in ["attention_mask", "prompt_attention_mask"] {
        let t = &header[name];
        assert_eq!(t["dtype"], "I64", "{t}");
        let steps = t["shape"][1].as_u64().unwrap() as usize;
        let start = 8 + n + t["data_offsets"][0].as_u64().unwrap() as usize;
        // Row 2 (the third sample) all 0.
        let mut bytes = golden.clone();
        bytes[start + 2 * steps * 8..start + 3 * steps * 8].fill(0);
        let inputs = tmp.path().join(format!("{name}.safetensors"));
        std::fs::write(&inputs, &bytes).unwrap();
        let e = fails(&[
            "model",
            "forward",
            "--weights",
            s(&w),
            "--inputs",
            s(&inputs),
            "--out",
            s(&out),
            "--n-head",
            "1",
        ]);
        assert!(e.contains(&format!("`{name}` row 2 is all 0")), "{e}");
        assert!(!out.exists());
    }
}

/// `train --pack --out DIR` refuses a DIR that holds a solo run, as `train
/// --config` refuses one that holds a run; before, the pack's record and runs went in beside it.
#[test]
fn round3_a_pack_is_not_written_into_a_solo_runs_directory() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let solo = tmp.path().join("solo");
    train(&cfg, &solo, &["--iterations", "1"]);
    let before: Vec<_> =
        std::fs::read_dir(&solo).unwrap().map(|e| e.unwrap().file_name()).collect();
    let b = variant(&cfg, "run", "seed", "1");
    let e = fails(&["train", "--pack", s(&cfg), s(&b), "--out", s(&solo)]);
    assert!(e.contains("holds a run") && e.contains("pick another --out"), "{e}");
    let after: Vec<_> = std::fs::read_dir(&solo).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(after, before, "nothing written into the solo run's directory");
}
