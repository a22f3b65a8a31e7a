//! Flat HDF5 files (the D4RL layout) read into step arrays (`pdt_data::flat_hdf5`): files written
//! by h5py itself (`tests/fixtures/hdf5/make_fixtures.py`), compressed and not, with numpy's bools,
//! 32- and 64-bit numbers, and the task in a named field; bad files refused naming the file and
//! the dataset.

use pdt_data::flat::FlatSteps;
use pdt_data::flat_hdf5::read_flat_hdf5;
use std::path::PathBuf;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/hdf5").join(name)
}

/// What `make_fixtures.py` wrote.
fn expected() -> FlatSteps {
    FlatSteps {
        obs_dim: 2,
        act_dim: 2,
        observations: (0..12).map(|x| x as f32).collect(),
        actions: (0..12).map(|x| ((x + 1) as f64 / 20.0) as f32).collect(),
        rewards: vec![1.0, 1.0, 5.0, 5.0, 5.0, 2.0],
        terminals: vec![false, true, false, false, false, false],
        timeouts: vec![false, false, false, false, true, true],
        task_ids: vec![1, 1, 1, 1, 1, 0],
    }
}

#[test]
fn a_d4rl_layout_file_is_read_and_its_other_datasets_are_named() {
    let got = read_flat_hdf5(&fixture("flat-d4rl.h5"), 2, 2, "task_ids").unwrap();
    assert_eq!(got.steps, expected());
    assert_eq!(got.ignored, ["infos/goal", "metadata/algorithm", "next_observations"]);
    let tasks = got.steps.split_by_task(&fixture("flat-d4rl.h5"), 2).unwrap();
    assert_eq!(tasks[&1].trajectories.len(), 2);
    assert_eq!(tasks[&0].trajectories.len(), 1);
}

#[test]
fn the_task_comes_from_a_named_field_and_n_by_1_flags_are_taken() {
    let got = read_flat_hdf5(&fixture("flat-infos-task.h5"), 2, 2, "infos/task").unwrap();
    assert_eq!(got.steps, expected());
    assert!(got.ignored.is_empty(), "{:?}", got.ignored);
}

#[test]
fn bad_files_are_refused_naming_the_file_and_the_dataset() {
    let cases = [
        ("flat-d4rl.h5", 3, 2, "task_ids", "`observations` has shape [6, 2]; expected [N, 3]"),
        ("flat-d4rl.h5", 2, 2, "infos/task", "no dataset `infos/task`"),
        ("flat-no-timeouts.h5", 2, 2, "task_ids", "no dataset `timeouts`"),
        ("flat-float-task.h5", 2, 2, "task_ids", "`task_ids` holds floating-point values"),
        ("flat.npz", 2, 2, "task_ids", "not a readable HDF5 file"),
    ];
    for (file, obs, act, field, want) in cases {
        let e = read_flat_hdf5(&fixture(file), obs, act, field).expect_err(file).to_string();
        assert!(e.contains(file) && e.contains(want), "{file}: {e}");
    }
    let e = read_flat_hdf5(&fixture("absent.h5"), 2, 2, "task_ids").unwrap_err().to_string();
    assert!(e.contains("absent.h5") && e.contains("not a readable HDF5 file"), "{e}");
}
