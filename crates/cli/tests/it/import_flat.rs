//! `promptdt data import --hdf5`: a flat HDF5 file (D4RL's layout, written by h5py) gives the same
//! files, byte for byte, as the same steps in an `.npz`; the task column may be any named field.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;
use cli::{fails, ok, s};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../data/tests/fixtures/hdf5").join(name)
}

fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| {
            (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap())
        })
        .collect()
}

#[test]
fn hdf5_and_npz_of_the_same_steps_import_to_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let import = |flag: &str, file: &str, task_field: &str, out: &str| {
        let out = tmp.path().join(out);
        let (f, o) = (fixture(file), out.clone());
        let args = ["data", "import", "--env", "point_robot", flag, s(&f), "--out", s(&o)];
        let msg =
            ok(&[&args[..], &["--task-field", task_field, "--prompt-rule", "best:1"]].concat());
        (msg, files(&out))
    };
    let (from_npz, npz_files) = import("--npz", "flat.npz", "task_ids", "npz");
    let (from_h5, h5_files) = import("--hdf5", "flat-d4rl.h5", "task_ids", "h5");
    let (_, infos_files) = import("--hdf5", "flat-infos-task.h5", "infos/task", "infos");
    assert!(from_npz.contains("imported 6 steps of 2 tasks of point_robot"), "{from_npz}");
    assert!(from_h5.contains("imported 6 steps of 2 tasks of point_robot"), "{from_h5}");
    assert!(
        from_h5.contains(
            "left out (not step arrays): infos/goal, metadata/algorithm, next_observations"
        ),
        "{from_h5}"
    );
    let names: Vec<&String> = npz_files.keys().collect();
    assert_eq!(
        names,
        [
            "point_robot-0-expert.safetensors",
            "point_robot-0-prompt-expert.safetensors",
            "point_robot-1-expert.safetensors",
            "point_robot-1-prompt-expert.safetensors"
        ]
    );
    assert_eq!(npz_files, h5_files);
    assert_eq!(npz_files, infos_files);
}

#[test]
fn a_bad_hdf5_file_is_refused_naming_it_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    for (file, field, want) in [
        ("flat-no-timeouts.h5", "task_ids", "no dataset `timeouts`"),
        ("flat-d4rl.h5", "infos/task", "no dataset `infos/task`"),
        ("flat.npz", "task_ids", "not a readable HDF5 file"),
    ] {
        let out = tmp.path().join(file);
        let f = fixture(file);
        let args = ["data", "import", "--env", "point_robot", "--hdf5", s(&f), "--out", s(&out)];
        let e = fails(&[&args[..], &["--task-field", field]].concat());
        assert!(e.contains(file) && e.contains(want), "{file}: {e}");
        assert!(!out.exists(), "{file}: wrote {}", out.display());
    }
    let e = fails(&["data", "import", "--env", "point_robot", "--out", s(tmp.path())]);
    assert!(e.contains("--npz") || e.contains("--hdf5"), "{e}");
}

/// Makes the Minari dataset `id` under `minari_dir` with `py`: three point-robot episodes whose reset
/// options name their task in `goal_name` (tasks 3, 5, 3), or carry no label when `labelled` is false.
fn make_minari(py: &Path, minari_dir: &Path, id: &str, labelled: bool) {
    let script = format!(
        r#"
import warnings, numpy as np, gymnasium as gym, minari
warnings.simplefilter("ignore")
rng = np.random.default_rng(0)
bufs = [minari.data_collector.EpisodeBuffer(
    id=i, observations=rng.standard_normal((T + 1, 2)).astype(np.float32),
    actions=rng.uniform(-0.1, 0.1, (T, 2)).astype(np.float32), rewards=-np.arange(T, dtype=float) - i,
    terminations=np.zeros(T, bool), truncations=np.arange(T) == T - 1,
    options={{"goal_name": g}} if {labelled} else {{}})
    for i, (T, g) in enumerate([(4, 3), (6, 5), (5, 3)])]
minari.create_dataset_from_buffers("{id}", bufs, observation_space=gym.spaces.Box(-9, 9, (2,), np.float32),
    action_space=gym.spaces.Box(-0.1, 0.1, (2,), np.float32), algorithm_name="x", author="x",
    author_email="x", code_permalink="x", description="x")
"#,
        labelled = if labelled { "True" } else { "False" }
    );
    let out = Command::new(py)
        .args(["-c", &script])
        .env("MINARI_DATASETS_PATH", minari_dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn a_minari_dataset_of_any_environment_imports_through_the_cli_as_through_python() {
    let Some(py) = pdt_testkit::python::worker_python() else { return };
    if !Command::new(&py).args(["-c", "import minari"]).status().unwrap().success() {
        // `make python-test` installs minari (PROMPTDT_PY_EXTRAS=minari) and requires it there.
        let require = std::env::var(pdt_testkit::python::REQUIRE_VAR).as_deref() == Ok("1");
        assert!(!require, "{} has no minari, and make python-test requires it", py.display());
        eprintln!("skipped: {} has no minari", py.display());
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let minari_dir = tmp.path().join("minari");
    make_minari(&py, &minari_dir, "user/point/goals-v0", true);
    make_minari(&py, &minari_dir, "user/point/none-v0", false);
    let run = |id: &str, out: &Path| {
        let args: Vec<String> =
            ["data", "import", "--env", "point_robot", "--minari", id, "--out", s(out)]
                .into_iter()
                .chain(["--task-field", "goal_name", "--prompt-rule", "best:1"])
                .map(String::from)
                .collect();
        let o = Command::new(env!("CARGO_BIN_EXE_promptdt"))
            .args(&args)
            .env("PROMPTDT_PYTHON", &py)
            .env("MINARI_DATASETS_PATH", &minari_dir)
            .output()
            .unwrap();
        (args, o)
    };
    let cli_out = tmp.path().join("cli");
    let (args, o) = run("user/point/goals-v0", &cli_out);
    let msg = cli::check_ok(&args, o);
    assert!(
        msg.contains("imported Minari dataset user/point/goals-v0") && msg.contains("(4 files)"),
        "{msg}"
    );
    // Python's own import of the same dataset: the same files, byte for byte.
    let py_out = tmp.path().join("py");
    let code = format!(
        "import promptdt; promptdt.import_minari('user/point/goals-v0', r'{}', env='point_robot', \
         mode='expert', task_field='goal_name', prompt_rule='best:1')",
        py_out.display()
    );
    let o = Command::new(&py)
        .args(["-c", &code])
        .env("MINARI_DATASETS_PATH", &minari_dir)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cli_files = files(&cli_out);
    let names: Vec<&String> = cli_files.keys().collect();
    assert_eq!(
        names,
        [
            "point_robot-3-expert.safetensors",
            "point_robot-3-prompt-expert.safetensors",
            "point_robot-5-expert.safetensors",
            "point_robot-5-prompt-expert.safetensors"
        ]
    );
    assert_eq!(cli_files, files(&py_out));
    let task3 =
        pdt_data::native::read_task_dataset(&cli_out.join("point_robot-3-expert.safetensors"))
            .unwrap();
    assert_eq!(task3.trajectories.iter().map(|t| t.len()).collect::<Vec<_>>(), [4, 5]);
    // No labels: refused naming the episode and the field; nothing written.
    let bad_out = tmp.path().join("bad");
    let (args, o) = run("user/point/none-v0", &bad_out);
    let e = cli::check_fails(&args, o);
    assert!(e.contains("episode 0: no task label: no 'goal_name' in its options or infos"), "{e}");
    assert!(!bad_out.exists() || std::fs::read_dir(&bad_out).unwrap().next().is_none());
}
