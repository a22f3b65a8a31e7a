//! `promptdt collect` for a MuJoCo family on a budget of seconds: RL training, an interruption and
//! `--resume`, the datasets, and `--from-pretrained` on the committed experts.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{ok, promptdt, repo};
use std::path::Path;

const TINY: [&str; 14] = [
    "--steps",
    "800",
    "--learning-starts",
    "200",
    "--hidden",
    "16,16",
    "--batch-size",
    "32",
    "--checkpoint-every",
    "400",
    "--episodes",
    "2",
    "--prompt-episodes",
    "1",
];

fn collect(run: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec!["collect", "--env", "cheetah_dir", "--threads", "1"];
    let (run, out) = (run.to_str().unwrap(), out.to_str().unwrap());
    args.extend(["--run-dir", run, "--out", out]);
    args.extend(TINY);
    args.extend(extra);
    ok(&args)
}

#[test]
fn collect_trains_is_interrupted_resumes_and_writes_the_same_datasets() {
    let tmp = tempfile::tempdir().unwrap();
    let p = |s: &str| tmp.path().join(s);
    let full = collect(&p("run-a"), &p("data-a"), &[]);
    assert!(full.contains("trained sac on cheetah_dir for 800 steps"), "{full}");
    assert!(full.contains("wrote 12 files"), "{full}");

    // Interrupted after 400 steps of this invocation, then resumed.
    let stopped = collect(&p("run-b"), &p("data-b"), &["--stop-after", "400"]);
    assert!(stopped.contains("continue with --resume"), "{stopped}");
    assert!(!p("data-b").exists(), "no datasets before training ends");
    let again = promptdt(&[
        "collect",
        "--env",
        "cheetah_dir",
        "--run-dir",
        p("run-b").to_str().unwrap(),
        "--out",
        p("data-b").to_str().unwrap(),
    ]);
    assert!(!again.status.success(), "a second start in the same run directory is refused");
    assert!(String::from_utf8_lossy(&again.stderr).contains("--resume"));
    collect(&p("run-b"), &p("data-b"), &["--resume"]);

    for name in ["agent/expert.safetensors", "agent/medium.safetensors", "episodes.csv"] {
        let a = std::fs::read(p("run-a").join(name)).unwrap();
        let b = std::fs::read(p("run-b").join(name)).unwrap();
        assert!(a == b, "{name}: the resumed run differs from the uninterrupted one");
    }
    let mut files: Vec<_> =
        std::fs::read_dir(p("data-a")).unwrap().map(|e| e.unwrap().file_name()).collect();
    files.sort();
    assert_eq!(files.len(), 13, "{files:?}"); // 2 tasks x 3 modes x (D_i, P_i) + dataset.json
    for f in &files {
        let a = std::fs::read(p("data-a").join(f)).unwrap();
        let b = std::fs::read(p("data-b").join(f)).unwrap();
        assert!(a == b, "{f:?} differs");
    }
    let card = std::fs::read_to_string(p("data-a/dataset.json")).unwrap();
    assert!(card.contains("\"algorithm\": \"sac\""), "{card}");

    // The written data is what `data inspect` reads.
    let inspect = ok(&["data", "inspect", p("data-a").to_str().unwrap()]);
    assert!(inspect.contains("12 files"), "{inspect}");
}

/// A run fine-tuned on one task (`--resume --tasks`), per-task experts from both (`agent
/// combine`), and datasets from the combined agent.
#[test]
fn fine_tune_combine_and_collect_from_the_combined_agent() {
    let tmp = tempfile::tempdir().unwrap();
    let p = |s: &str| tmp.path().join(s);
    collect(&p("run-a"), &p("data-a"), &[]);
    std::fs::create_dir_all(p("run-c/snapshots")).unwrap();
    // A copy of the run (`cp -r` without `agent/`).
    for f in ["checkpoint.safetensors", "config.json", "episodes.csv"] {
        std::fs::copy(p("run-a").join(f), p("run-c").join(f)).unwrap();
    }
    for e in std::fs::read_dir(p("run-a/snapshots")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), p("run-c/snapshots").join(e.file_name())).unwrap();
    }
    let (run_c, data_c) = (p("run-c"), p("data-c"));
    let tuned = ok(&[
        "collect",
        "--env",
        "cheetah_dir",
        "--threads",
        "1",
        "--run-dir",
        run_c.to_str().unwrap(),
        "--out",
        data_c.to_str().unwrap(),
        "--episodes",
        "2",
        "--prompt-episodes",
        "1",
        "--resume",
        "--tasks",
        "1",
        "--steps",
        "1000",
    ]);
    assert!(tuned.contains("for 1000 steps"), "{tuned}");
    let config = std::fs::read_to_string(p("run-c/config.json")).unwrap();
    assert!(config.contains("\"tasks\": [\n    1\n  ]"), "{config}");

    let snaps = format!(
        "{},{}",
        p("run-a/snapshots").to_str().unwrap(),
        p("run-c/snapshots").to_str().unwrap()
    );
    let out = ok(&[
        "agent",
        "combine",
        "--base",
        p("run-a/agent").to_str().unwrap(),
        "--snapshots",
        &snaps,
        "--out",
        p("combined").to_str().unwrap(),
        "--eval-episodes",
        "2",
        "--deterministic-datasets",
    ]);
    assert!(out.contains("mean expert return"), "{out}");
    let card = std::fs::read_to_string(p("combined/agent.json")).unwrap();
    assert!(card.contains("task_experts"), "{card}");
    let from_combined = |out: &str, extra: &[&str]| {
        let (agent, out) = (p("combined"), p(out));
        let mut args = vec!["collect", "--env", "cheetah_dir", "--from-pretrained"];
        args.extend(["--pretrained-dir", agent.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        args.extend(["--episodes", "2", "--prompt-episodes", "1"]);
        args.extend(extra);
        ok(&args)
    };
    let data = from_combined("data-comb", &[]);
    assert!(data.contains("wrote 12 files"), "{data}");
    let dcard = std::fs::read_to_string(p("data-comb/dataset.json")).unwrap();
    assert!(dcard.contains("expert_per_task"), "{dcard}");
    // The agent asks for noiseless data; --explore overrides it.
    assert!(dcard.contains("\"noise\": \"deterministic\""), "{dcard}");
    from_combined("data-explore", &["--explore"]);
    let ecard = std::fs::read_to_string(p("data-explore/dataset.json")).unwrap();
    assert!(ecard.contains("\"noise\": \"explore\""), "{ecard}");

    // The base directory cannot be overwritten, and a missing snapshot path is named.
    let bad = promptdt(&[
        "agent",
        "combine",
        "--base",
        p("run-a/agent").to_str().unwrap(),
        "--snapshots",
        p("nowhere").to_str().unwrap(),
        "--out",
        p("c2").to_str().unwrap(),
    ]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("nowhere"));
}

/// The committed experts rebuild datasets without training (a few episodes here; the full rebuild
/// is `promptdt collect --env <family> --from-pretrained`).
#[test]
fn from_pretrained_uses_the_committed_agents() {
    let tmp = tempfile::tempdir().unwrap();
    // Every family whose datasets come from an RL agent (not its scripted policies).
    let rl_families = pdt_envs::FAMILY_NAMES
        .into_iter()
        .filter(|f| pdt_envs::family(f).is_ok_and(|f| f.scripted().is_none()));
    for family in rl_families {
        let agent = repo(&format!("pretrained/{family}"));
        if !agent.join("agent.json").exists() {
            eprintln!("skipped {family}: no committed agent in {}", agent.display());
            continue;
        }
        let out = tmp.path().join(family);
        let stdout = ok(&[
            "collect",
            "--env",
            family,
            "--from-pretrained",
            "--pretrained-dir",
            agent.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--episodes",
            "1",
            "--prompt-episodes",
            "1",
        ]);
        assert!(stdout.contains("using the pretrained agent"), "{stdout}");
        assert!(out.join("dataset.json").exists());
    }
}

#[test]
fn collect_bad_inputs_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let err = |args: &[&str]| {
        let out = promptdt(args);
        assert!(!out.status.success(), "{args:?} should fail");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = err(&[
        "collect",
        "--env",
        "cheetah_vel",
        "--tasks",
        "41",
        "--steps",
        "10",
        "--run-dir",
        tmp.path().join("r").to_str().unwrap(),
    ]);
    assert!(e.contains("41"), "{e}");
    let e = err(&[
        "collect",
        "--env",
        "ant_dir",
        "--resume",
        "--run-dir",
        tmp.path().join("none").to_str().unwrap(),
    ]);
    assert!(e.contains("no checkpoint"), "{e}");
    let e = err(&[
        "collect",
        "--env",
        "cheetah_dir",
        "--algorithm",
        "ppo",
        "--run-dir",
        tmp.path().join("p").to_str().unwrap(),
    ]);
    assert!(e.contains("ppo"), "{e}");
    let e = err(&[
        "collect",
        "--env",
        "cheetah_dir",
        "--from-pretrained",
        "--pretrained-dir",
        tmp.path().to_str().unwrap(),
    ]);
    assert!(e.contains("agent.json"), "{e}");
}
