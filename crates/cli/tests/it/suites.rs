//! A task suite written as a file goes through the front ends without any of them naming it
//! (`docs/your-own-tasks.md`): the suite file and its data are all a user adds, no Rust.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{fails, ok, s, TINY};
use std::path::{Path, PathBuf};

/// A suite with data only (no `[environment]`): 5 tasks on a line, 3 trained on, 2 held out; the
/// one file the tests of the front ends share.
const SUITE: &str = include_str!("../../../../examples/toy_line/suite.toml");

/// Episodes of task `task`: the agent moves towards its goal on a line, rewarded for closeness.
fn episodes(task: usize, n: usize) -> pdt_data::TaskDataset {
    let goal = task as f32 * 0.25;
    let trajectories = (0..n)
        .map(|e| {
            let (mut obs, mut act, mut rew) = (vec![], vec![], vec![]);
            let mut x = -0.5 + 0.1 * e as f32;
            for _ in 0..10 {
                let a = (goal - x).clamp(-1.0, 1.0) * 0.5;
                obs.extend([x, goal - x]);
                act.push(a);
                x += a;
                rew.push(1.0 - (goal - x).abs());
            }
            let mut truncated = vec![false; 10];
            truncated[9] = true;
            pdt_data::Trajectory::new(2, 1, obs, act, rew, vec![false; 10], truncated).unwrap()
        })
        .collect();
    pdt_data::TaskDataset::new(trajectories).unwrap()
}

/// The suite file and its data (written as a user's script would, in the native format), and a
/// tiny experiment file naming the suite by its path.
fn suite_setup(dir: &Path) -> (PathBuf, PathBuf) {
    let suite = dir.join("my_tasks.toml");
    std::fs::write(&suite, SUITE).unwrap();
    let data = dir.join("data");
    std::fs::create_dir_all(&data).unwrap();
    for task in 0..5 {
        for (mode, n) in [("expert", 4), ("prompt-expert", 2)] {
            let path = data.join(format!("toy_line-{task}-{mode}.safetensors"));
            let meta = pdt_data::native::FileMeta::new("toy_line", task, mode);
            pdt_data::native::write_task_dataset(&path, &episodes(task, n), &meta).unwrap();
        }
    }
    let cfg = dir.join("exp.toml");
    let text = TINY.replace("name = \"point_robot\"", &format!("name = {:?}", s(&suite)));
    assert_ne!(text, TINY);
    std::fs::write(&cfg, format!("{text}\n[data]\ndir = {:?}\n", s(&data))).unwrap();
    (suite, cfg)
}

#[test]
fn a_suite_trains_and_resumes_from_the_run_copy_without_an_environment() {
    let tmp = tempfile::tempdir().unwrap();
    let (suite, cfg) = suite_setup(tmp.path());
    let run = tmp.path().join("run");
    let out = ok(&["train", "--config", s(&cfg), "--out", s(&run), "--quiet"]);
    // No environment to evaluate in: said, not failed.
    assert!(out.contains("note:") && out.contains("declares no [environment]"), "{out}");
    let info = std::fs::read_to_string(run.join("run.json")).unwrap();
    assert!(info.contains("\"toy_line\""), "{info}");
    // The run keeps the suite as it read it, and records the suite's absolute path.
    assert_eq!(std::fs::read_to_string(run.join("suite.toml")).unwrap(), SUITE);
    let config = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(config.contains(&format!("name = {:?}", s(&suite))), "{config}");
    // Evaluated offline instead, at the cadence of evaluations in an environment (after
    // iterations 1, 5 and the last, 8), into a log of its own: no return is written anywhere.
    assert_eq!(std::fs::read_to_string(run.join("eval.jsonl")).unwrap(), "");
    let offline = offline_lines(&run);
    assert_eq!(offline.iter().map(|l| l.0).collect::<Vec<_>>(), [1, 1, 5, 5, 8, 8]);
    assert_eq!(offline.iter().map(|l| l.1).collect::<Vec<_>>(), [3, 4, 3, 4, 3, 4]);
    assert!(offline.iter().all(|l| l.2.is_finite() && l.2 > 0.0), "{offline:?}");
    assert!(std::fs::read_to_string(run.join("offline_eval.csv")).unwrap().contains("action_mse"));

    // Without the original the run resumes from its copy.
    let moved = tmp.path().join("moved.toml");
    std::fs::rename(&suite, &moved).unwrap();
    ok(&["train", "--resume", s(&run), "--iterations", "10", "--quiet"]);
    // The offline log goes on where the checkpoint left it (9 is 1 + 2 x 4, 10 the last).
    let resumed = offline_lines(&run);
    assert_eq!(resumed[..6], offline[..]);
    assert_eq!(resumed.iter().map(|l| l.0).collect::<Vec<_>>(), [1, 1, 5, 5, 8, 8, 9, 9, 10, 10]);
    // An edited original is refused, naming both files.
    std::fs::write(&suite, SUITE.replace("g4", "g5")).unwrap();
    let e = fails(&["train", "--resume", s(&run), "--iterations", "12", "--quiet"]);
    assert!(e.contains("changed since the run was trained") && e.contains("suite.toml"), "{e}");
    std::fs::rename(&moved, &suite).unwrap();

    // Collecting needs a policy: said, with where its data may come from otherwise.
    let e = fails(&["collect", "--env", s(&suite), "--out", s(&tmp.path().join("c"))]);
    assert!(e.contains("needs a policy, --policy") && e.contains("data import"), "{e}");
    // With one, the suite's missing [environment] is named.
    let e = fails(&[
        "collect",
        "--env",
        s(&suite),
        "--policy",
        "m:f",
        "--out",
        s(&tmp.path().join("c")),
    ]);
    assert!(e.contains("declares no [environment] to collect in"), "{e}");
    assert!(!tmp.path().join("c").exists(), "nothing written");
    // `promptdt eval` evaluates such a run offline: an action error, said to be one, written to
    // its own file, the same for the same checkpoint.
    let out = ok(&["eval", "--run", s(&run)]);
    assert!(out.contains("action MSE") && out.contains("not a return"), "{out}");
    let written = std::fs::read_to_string(run.join("eval_offline.json")).unwrap();
    assert!(
        written.contains("\"metric\": \"action_mse\"") && written.contains("\"iteration\": 10")
    );
    ok(&["eval", "--run", s(&run)]);
    assert_eq!(std::fs::read_to_string(run.join("eval_offline.json")).unwrap(), written);
    assert!(!run.join("eval_final.json").exists());
    // Asking for episodes of it is a clear error, not a panic.
    let e = fails(&["eval", "--run", s(&run), "--episodes", "1"]);
    assert!(e.contains("evaluated offline") && e.contains("no [environment]"), "{e}");

    // The report shows it as an action error, in a table of its own, never as a return.
    let rep = tmp.path().join("report");
    let out = ok(&["report", s(&run), "--out", s(&rep)]);
    assert!(out.contains("Held-out action error") && out.contains("action MSE"), "{out}");
    assert!(!out.contains("Return on held-out"), "{out}");
    let csv = std::fs::read_to_string(rep.join("offline.csv")).unwrap();
    assert!(csv.starts_with("env,method,task,metric,") && csv.contains(",action_mse,"), "{csv}");
}

/// A held-out task without data cannot be evaluated offline (nor trained beside): refused before
/// anything is written, naming the task and the file looked for.
#[test]
fn a_held_out_task_without_data_is_refused_naming_it_and_its_file() {
    let tmp = tempfile::tempdir().unwrap();
    let (_suite, cfg) = suite_setup(tmp.path());
    std::fs::remove_file(tmp.path().join("data/toy_line-4-expert.safetensors")).unwrap();
    let run = tmp.path().join("run");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run), "--quiet"]);
    assert!(e.contains("task toy_line-4") && e.contains("toy_line-4-expert.safetensors"), "{e}");
    assert!(!run.join("config.toml").exists() && !run.join("offline_eval.jsonl").exists());
}

/// `(iteration, task_index, action_mse)` of each line of the run's `offline_eval.jsonl`.
fn offline_lines(run: &Path) -> Vec<(u64, u64, f64)> {
    let text = std::fs::read_to_string(run.join("offline_eval.jsonl")).unwrap();
    text.lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            assert_eq!(v["eval_on"], "test", "{l}");
            let n = |k: &str| v[k].as_u64().unwrap();
            (n("iteration"), n("task_index"), v["action_mse"].as_f64().unwrap())
        })
        .collect()
}

#[test]
fn a_suite_split_and_bad_suite_are_checked_by_the_front_end() {
    let tmp = tempfile::tempdir().unwrap();
    let (suite, cfg) = suite_setup(tmp.path());
    // The second split by name.
    let ood = tmp.path().join("ood.toml");
    let text = std::fs::read_to_string(&cfg).unwrap();
    let text = text.replacen("[env]\n", "[env]\nsplit = \"ood\"\n", 1);
    std::fs::write(&ood, text).unwrap();
    let run = tmp.path().join("run-ood");
    ok(&["train", "--config", s(&ood), "--out", s(&run), "--quiet", "--iterations", "2"]);
    let info = std::fs::read_to_string(run.join("run.json")).unwrap();
    assert!(info.contains("\"ood\""), "{info}");
    // A bad field stops `train` before anything is written, naming the file and the field.
    std::fs::write(&suite, SUITE.replace("test = [\"g3\", \"g4\"]", "test = [\"g3\", \"g9\"]"))
        .unwrap();
    let bad = tmp.path().join("run-bad");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&bad), "--quiet"]);
    assert!(e.contains("my_tasks.toml") && e.contains("splits.main.test[1]"), "{e}");
    assert!(!bad.join("config.toml").exists() && !bad.join("suite.toml").exists());
}

/// The arrays of a flat `.npz`: name, values (as f64), row width (0: one value a step).
type Arrays = Vec<(&'static str, Vec<f64>, i64)>;

/// A bad-data case: what it is, how it spoils the arrays, what the error must say.
type BadCase = (&'static str, fn(&mut Arrays), &'static str);

/// Every step of `tasks`' episodes as flat arrays in an `.npz` at `path`; `edit` changes them
/// first.
fn write_flat_npz(path: &Path, tasks: &[usize], edit: impl Fn(&mut Arrays)) {
    let (mut obs, mut act, mut rew, mut term, mut tout, mut ids) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    for &task in tasks {
        for t in episodes(task, 3).trajectories {
            obs.extend(t.observations.iter().map(|&x| f64::from(x)));
            act.extend(t.actions.iter().map(|&x| f64::from(x)));
            rew.extend(t.rewards.iter().map(|&x| f64::from(x)));
            term.extend(t.terminated.iter().map(|&x| f64::from(u8::from(x))));
            tout.extend(t.truncated.iter().map(|&x| f64::from(u8::from(x))));
            ids.extend(std::iter::repeat_n(task as f64, t.len()));
        }
    }
    let mut arrays: Arrays = vec![
        ("observations", obs, 2),
        ("actions", act, 1),
        ("rewards", rew, 0),
        ("terminals", term, 0),
        ("timeouts", tout, 0),
        ("task_ids", ids, 0),
    ];
    edit(&mut arrays);
    let tensors: Vec<(&str, tch::Tensor)> = arrays
        .into_iter()
        .map(|(name, v, width)| {
            let t = tch::Tensor::from_slice(&v);
            let t = if width > 0 { t.reshape([-1, width]) } else { t };
            let t = match name {
                // tch writes no bool arrays; numpy's `|b1` reads as well.
                "terminals" | "timeouts" => t.to_kind(tch::Kind::Uint8),
                "task_ids" => t.to_kind(tch::Kind::Int64),
                _ => t.to_kind(tch::Kind::Float),
            };
            (name, t)
        })
        .collect();
    tch::Tensor::write_npz(&tensors, path).unwrap();
}

#[test]
fn flat_data_is_imported_into_a_suite_and_bad_data_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let (suite, _) = suite_setup(tmp.path());
    let npz = tmp.path().join("flat.npz");
    write_flat_npz(&npz, &[0, 1, 2, 3], |_| {});
    let out = tmp.path().join("imported");
    let args = ["data", "import", "--env", s(&suite), "--npz", s(&npz), "--out", s(&out)];
    let msg = ok(&[&args[..], &["--prompt-rule", "best:2"]].concat());
    assert!(msg.contains("imported 120 steps of 4 tasks of toy_line"), "{msg}");
    assert!(msg.contains("no data for tasks 4"), "{msg}");
    for task in 0..4 {
        let ds = pdt_data::native::read_task_dataset(
            &out.join(format!("toy_line-{task}-expert.safetensors")),
        )
        .unwrap();
        assert_eq!(ds, episodes(task, 3), "task {task}");
        let p = pdt_data::native::read_task_dataset(
            &out.join(format!("toy_line-{task}-prompt-expert.safetensors")),
        )
        .unwrap();
        // The two best-return episodes, best first.
        let mut returns = ds.returns();
        returns.sort_by(|a, b| b.total_cmp(a));
        assert_eq!(p.returns(), returns[..2].to_vec(), "task {task}");
    }

    // Bad data: refused naming the file and the array, and nothing written.
    let cases: [BadCase; 4] = [
        (
            "unknown task",
            |a| a[5].1[40] = 7.0,
            "`task_ids` at step 40 is 7; the suite has tasks 0..5",
        ),
        ("NaN", |a| a[2].1[3] = f64::NAN, "`rewards` at step 3 is NaN"),
        ("wrong width", |a| a[0].2 = 1, "`observations` has shape [240, 1]; expected [N, 2]"),
        ("missing", |a| drop(a.remove(4)), "no array `timeouts`"),
    ];
    for (what, edit, want) in cases {
        let bad = tmp.path().join("bad.npz");
        write_flat_npz(&bad, &[0, 1, 2, 3], edit);
        let out = tmp.path().join(format!("bad-{}", what.replace(' ', "-")));
        let args = ["data", "import", "--env", s(&suite), "--npz", s(&bad), "--out", s(&out)];
        let e = fails(&args);
        assert!(e.contains("bad.npz") && e.contains(want), "{what}: {e}");
        assert!(!out.exists() || std::fs::read_dir(&out).unwrap().next().is_none(), "{what}");
    }
}
