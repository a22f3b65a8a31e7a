//! `promptdt reproduce`: every experiment end to end at the smoke budget, finished runs skipped on a
//! second call, and `--emit jobs` run by plain `xargs -P 2` giving the same report as `reproduce`.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use std::path::{Path, PathBuf};
use std::process::Command;

/// The binary run in the checkout's root: (success, stdout, stderr).
fn promptdt(args: &[&str]) -> (bool, String, String) {
    let out = cli::promptdt_in(&repo(), args);
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn ok(args: &[&str]) -> String {
    cli::check_ok(args, cli::promptdt_in(&repo(), args))
}

/// The checkout's root.
fn repo() -> PathBuf {
    cli::repo("")
}

const EXPERIMENTS: [&str; 8] = [
    "fig2",
    "table1",
    "fig3",
    "fig4",
    "appendix_prompt_length_mt_bc",
    "appendix_finetune_mt_bc",
    "appendix_finetune_macaw",
    "prompt_control",
];

#[test]
fn list_names_every_experiment_with_its_budgets() {
    let out = ok(&["reproduce", "--list"]);
    for e in EXPERIMENTS {
        assert!(out.contains(e), "{e} missing from:\n{out}");
    }
    assert!(out.contains("paper") && out.contains("cpu") && out.contains("smoke"), "{out}");
}

/// `promptdt reproduce --list | head`: the reader is gone before the first line is written. The
/// program ends quietly with success (it used to panic in `println!` on the broken pipe), and a
/// full disk is still an error that says what failed.
#[test]
fn list_into_a_closed_pipe_ends_quietly_and_a_full_disk_is_an_error() {
    // `reproduce --list` with its standard output on `stdout`: (success, stderr).
    let list_into = |stdout: std::process::Stdio| {
        let out = Command::new(env!("CARGO_BIN_EXE_promptdt"))
            .args(["reproduce", "--list"])
            .current_dir(repo())
            .stdout(stdout)
            .output()
            .unwrap();
        (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader); // closed before the child starts: every write gets EPIPE
    let (success, stderr) = list_into(writer.into());
    assert!(success, "{stderr}");
    assert!(stderr.is_empty(), "{stderr}");
    if let Ok(full) = std::fs::File::create("/dev/full") {
        let (success, stderr) = list_into(full.into());
        assert!(!success && stderr.contains("writing to standard output"), "{stderr}");
    }
}

#[test]
fn bad_input_is_refused_by_name() {
    let (ok1, _, err) = promptdt(&["reproduce", "fig9", "--budget", "smoke"]);
    assert!(!ok1 && err.contains("fig9") && err.contains("fig2"), "{err}");
    let (ok2, _, err) =
        promptdt(&["reproduce", "fig2", "--budget", "huge", "--out", "/nonexistent/x"]);
    assert!(!ok2 && err.contains("huge") && err.contains("smoke"), "{err}");
    let (ok3, _, err) = promptdt(&["reproduce", "fig2", "--budget", "smoke", "--emit", "slurm"]);
    assert!(!ok3 && err.contains("--emit slurm"), "{err}");
    // TF32 matmuls need a GPU to train on; jobs for one can be emitted anywhere, and carry it.
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("r");
    let out_s = out.to_str().unwrap();
    let tf32 = ["reproduce", "fig4", "--budget", "smoke", "--matmul", "tf32", "--out", out_s];
    let (ok4, _, err) = promptdt(&[&tf32[..], &["--device", "cpu"]].concat());
    assert!(!ok4 && err.contains("--matmul tf32 needs a CUDA device"), "{err}");
    assert!(!out.exists(), "nothing written");
    ok(&[&tf32[..], &["--device", "cuda", "--emit", "jobs"]].concat());
    let jobs = std::fs::read_to_string(out.join("jobs/fig4-smoke/jobs.txt")).unwrap();
    assert!(jobs.lines().all(|l| l.contains("'--matmul' 'tf32'")), "{jobs}");
}

/// Every experiment at the smoke budget, in one output directory (datasets collected once, shared
/// runs reused), then the emitted jobs of one experiment run by xargs into another directory.
#[test]
fn every_experiment_runs_at_smoke_and_emitted_jobs_give_the_same_report() {
    let tmp = tempfile::tempdir().unwrap();
    let a = tmp.path().join("a");
    let a_s = a.to_str().unwrap();
    for e in EXPERIMENTS {
        let out = ok(&["reproduce", e, "--budget", "smoke", "--out", a_s, "--jobs", "2"]);
        assert!(out.contains("report:"), "{e}: {out}");
        let report = a.join("reports").join(format!("{e}-smoke"));
        for f in ["report.md", "cells.csv", "curves.csv", "report.json"] {
            assert!(report.join(f).is_file(), "{e}: no {f}");
        }
    }
    // Figure 2: one curve plot per MuJoCo family, every non-pending cell with a result.
    let fig2 = a.join("reports/fig2-smoke");
    for env in ["cheetah_dir", "cheetah_vel", "ant_dir", "metaworld_reach", "dial"] {
        assert!(fig2.join(format!("curves_{env}.png")).is_file(), "{env}");
    }
    let cells = std::fs::read_to_string(fig2.join("cells.csv")).unwrap();
    assert_eq!(cells.lines().filter(|l| l.contains(",\"ran\",")).count(), 28, "{cells}");
    assert!(!cells.contains("not in promptdt yet"), "{cells}");
    // Meta-World reach's and Dial's cells report the success rate beside the return.
    for env in ["metaworld_reach", "dial"] {
        let run = a.join(format!("runs/{env}/prompt-dt/smoke/seed0/eval.jsonl"));
        assert!(std::fs::read_to_string(&run).unwrap().contains("success_rate"), "{env}");
    }
    // MACAW's cells ran (its adaptation logged with the evaluations)
    let macaw = a.join("runs/cheetah_vel/macaw/smoke/seed0/eval.jsonl");
    assert!(
        std::fs::read_to_string(&macaw).unwrap().contains("adapt_policy_steps"),
        "{}",
        macaw.display()
    );
    // Table 1 shares Figure 2's 1 x 5 Prompt-DT runs: a second call finds everything finished.
    let again = ok(&["reproduce", "table1", "--budget", "smoke", "--out", a_s, "--jobs", "2"]);
    assert!(again.contains("12 runs already finished, 0 started, 0 resumed"), "{again}");

    // While a sweep runs, a cell shows its finished seeds only: a second seed of one Table 1 cell,
    // made to look unfinished (its resume point set back to iteration 1 of 2), is left out, so the
    // cell is seed 0's result alone, marked partial.
    let table1 = a.join("reports/table1-smoke/cells.csv");
    let row = |csv: &str| -> Vec<String> {
        let line = csv.lines().find(|l| l.starts_with("\"cheetah_dir/prompt-dt-k1x2\"")).unwrap();
        line.split(',').map(str::to_string).collect()
    };
    let before = row(&std::fs::read_to_string(&table1).unwrap());
    let cell = "cheetah_dir/prompt-dt-k1x2/smoke";
    let seed1 = format!("{cell}/seed1");
    let two = ["reproduce", "table1", "--budget", "smoke", "--seeds", "2", "--out", a_s];
    ok(&[&two[..], &["--only", &seed1]].concat());
    let latest = a.join(format!("runs/{seed1}/checkpoints/latest.json"));
    let text = std::fs::read_to_string(&latest).unwrap();
    assert!(text.contains("\"iteration\": 2,"), "{text}");
    std::fs::write(&latest, text.replace("\"iteration\": 2,", "\"iteration\": 1,")).unwrap();
    ok(&[&two[..], &["--report-only"]].concat());
    let after = row(&std::fs::read_to_string(&table1).unwrap());
    assert_eq!(after[5], "\"partial: 1 of 2 seeds finished\"", "{after:?}");
    assert_eq!((&after[6], &after[9], &after[11]), (&before[6], &before[9], &before[11]));
    // With no seed of the cell finished, its running seeds are shown, but the paper's claims that
    // name it are not checked on them.
    let claim = || {
        let md = std::fs::read_to_string(a.join("reports/table1-smoke/report.md")).unwrap();
        md.lines().find(|l| l.contains("Cheetah-Dir: insensitive")).unwrap().to_string()
    };
    assert!(!claim().contains("not measured"), "{}", claim());
    let latest0 = a.join(format!("runs/{cell}/seed0/checkpoints/latest.json"));
    let text = std::fs::read_to_string(&latest0).unwrap();
    std::fs::write(&latest0, text.replace("\"iteration\": 2,", "\"iteration\": 1,")).unwrap();
    ok(&[&two[..], &["--report-only"]].concat());
    assert_eq!(row(&std::fs::read_to_string(&table1).unwrap())[5], "\"partial\"");
    let c = claim();
    assert!(c.contains("not measured") && c.contains("k1x2: ") && c.contains("(running"), "{c}");

    // The same experiment through --emit jobs + xargs, then --report-only.
    let b = tmp.path().join("b");
    let b_s = b.to_str().unwrap();
    let data = a.join("data");
    let common = ["--budget", "smoke", "--jobs", "2"];
    let mut args = vec!["reproduce", "fig4", "--out", a_s];
    args.extend(common);
    let mut emit = vec!["reproduce", "fig4", "--out", b_s, "--data-root", data.to_str().unwrap()];
    emit.extend(common);
    emit.extend(["--emit", "jobs", "--device", "cpu"]);
    ok(&emit);
    let jobs = b.join("jobs/fig4-smoke/jobs.txt");
    let lines = std::fs::read_to_string(&jobs).unwrap();
    assert_eq!(lines.lines().count(), 9); // fig4: 5 cells on the reference split, 4 on the paper one
                                          // Each job runs on the device asked for here, not on its own `auto`.
    assert!(lines.lines().all(|l| l.contains("'--device' 'cpu'")), "{lines}");
    assert!(b.join("jobs/fig4-smoke/run.slurm").is_file());
    let status = Command::new("sh")
        .arg("-c")
        .arg(format!("xargs -P 2 -I{{}} sh -c {{}} < '{}'", jobs.display()))
        .current_dir(repo())
        .status()
        .unwrap();
    assert!(status.success(), "xargs over the emitted jobs failed");
    let mut report = vec!["reproduce", "fig4", "--out", b_s, "--data-root", data.to_str().unwrap()];
    report.extend(common);
    report.push("--report-only");
    ok(&report);
    let read = |d: &Path| std::fs::read_to_string(d.join("reports/fig4-smoke/cells.csv")).unwrap();
    assert_eq!(read(&a), read(&b), "the emitted jobs gave another report");
    let curves =
        |d: &Path| std::fs::read_to_string(d.join("reports/fig4-smoke/curves.csv")).unwrap();
    assert_eq!(curves(&a), curves(&b));
}

/// The Slurm array script asks for what its tasks use: `--cpus-per-task` is the runs'
/// `--threads` (a pack's runs compute one at a time), a GPU (`--gres=gpu:1`, marked as
/// the place a site edits) only on `--device cuda`, and the jobs name the committed agents by an
/// absolute path that does not depend on the directory `--emit` ran in; agents that are not there
/// are refused before anything is written. Emitted from a directory other than the checkout.
#[test]
fn emitted_slurm_script_asks_for_what_the_runs_use() {
    let tmp = tempfile::tempdir().unwrap();
    let cwd = tmp.path().join("elsewhere"); // no `pretrained/` here
    std::fs::create_dir(&cwd).unwrap();
    let mut n = 0;
    // Emits fig4 at smoke with `extra` into a fresh --out: (run.slurm, jobs.txt).
    let mut emit = |extra: &[&str]| {
        n += 1;
        let out = tmp.path().join(format!("out{n}"));
        let mut args = vec!["reproduce", "fig4", "--budget", "smoke", "--emit", "jobs", "--out"];
        args.push(out.to_str().unwrap());
        args.extend(extra);
        cli::check_ok(&args, cli::promptdt_in(&cwd, &args));
        let read = |f: &str| std::fs::read_to_string(out.join("jobs/fig4-smoke").join(f)).unwrap();
        (read("run.slurm"), read("jobs.txt"))
    };
    let (slurm, jobs) = emit(&["--threads", "1", "--device", "cpu"]);
    assert!(slurm.contains("\n#SBATCH --cpus-per-task=1\n"), "{slurm}");
    assert!(!slurm.contains("--gres"), "{slurm}");
    let agents = repo().join("pretrained").canonicalize().unwrap();
    let agents = format!("'--pretrained-root' '{}'", agents.display());
    assert!(jobs.lines().all(|l| l.contains(&agents)), "{agents} missing from:\n{jobs}");
    let (slurm, _) = emit(&["--threads", "3", "--device", "cpu"]);
    assert!(slurm.contains("\n#SBATCH --cpus-per-task=3\n"), "{slurm}");
    // A GPU per task on CUDA, with the comment that says where a site edits it.
    let (slurm, jobs) = emit(&["--threads", "2", "--device", "cuda"]);
    assert!(slurm.contains("\n#SBATCH --gres=gpu:1\n"), "{slurm}");
    assert!(slurm.contains("The place to edit for a site"), "{slurm}");
    assert!(slurm.contains("\n#SBATCH --cpus-per-task=2\n"), "{slurm}");
    assert!(jobs.lines().all(|l| l.contains("'--device' 'cuda'")), "{jobs}");
    // sbatch reads #SBATCH lines up to the first command only.
    let first_command = slurm.lines().position(|l| !l.starts_with('#')).unwrap();
    assert!(slurm.lines().skip(first_command).all(|l| !l.starts_with("#SBATCH")), "{slurm}");
    // Packs of 3 seeds: the solo engine steps a pack's runs one after another, the batched
    // engine as one computation: either uses one run's threads.
    let pack = ["--seeds", "3", "--pack", "3", "--threads", "2", "--device", "cpu"];
    let (slurm, jobs) = emit(&[&pack[..], &["--pack-engine", "solo"]].concat());
    assert!(jobs.lines().any(|l| l.matches(",").count() == 2), "no pack of 3:\n{jobs}");
    assert!(slurm.contains("\n#SBATCH --cpus-per-task=2\n"), "{slurm}");
    let (slurm, _) = emit(&[&pack[..], &["--pack-engine", "batched"]].concat());
    assert!(slurm.contains("\n#SBATCH --cpus-per-task=2\n"), "{slurm}");

    // Agents that are not there: refused by name, nothing written.
    let out = tmp.path().join("none");
    let missing = tmp.path().join("no-agents");
    let args = [
        "reproduce",
        "fig4",
        "--budget",
        "smoke",
        "--emit",
        "jobs",
        "--out",
        out.to_str().unwrap(),
        "--pretrained-root",
        missing.to_str().unwrap(),
    ];
    let err = cli::check_fails(&args, cli::promptdt_in(&cwd, &args));
    let agent = missing.join("ant_dir/agent.json");
    assert!(err.contains("--pretrained-root") && err.contains(agent.to_str().unwrap()), "{err}");
    assert!(!out.join("jobs").exists(), "jobs written for agents that are not there");
}
