//! The 42 prompt sets of the reference release (`official-prompts/` of its data, found by
//! `pdt_testkit::reference`: `../shared/data` beside the checkout or `PROMPTDT_REFERENCE_DATA`; see
//! its README): read with the safe pickle reader and checked against the README's shapes and return
//! figures. Without the data each test is skipped (and fails under
//! `PROMPTDT_REQUIRE_REFERENCE_DATA=1`, as in CI).

use std::fs;
use std::path::{Path, PathBuf};

use pdt_data::inspect::{inspect_path, render_table};
use pdt_data::pickle::{self, PyValue};
use pdt_data::reference::{load_pickle, ReferenceOptions, TerminalsAs};
use pdt_data::{native, TaskDataset};
use pdt_testkit::reference::{official_prompt, official_prompts};

fn official_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .filter_map(|e| Some(e.ok()?.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "pkl"))
        .collect();
    files.sort();
    files
}

fn load(dir: &Path, task: &str) -> TaskDataset {
    let path = dir.join(format!("{task}-prompt-expert.pkl"));
    load_pickle(&path, &ReferenceOptions::default()).expect("load").dataset
}

#[test]
fn all_42_files_load_with_the_documented_layout() {
    let Some(dir) = official_prompts() else { return };
    let files = official_files(&dir);
    assert_eq!(files.len(), 42);
    for path in &files {
        let name = path.display();
        let loaded = load_pickle(path, &ReferenceOptions::default())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let ds = &loaded.dataset;
        assert_eq!((ds.trajectories.len(), ds.obs_dim, ds.act_dim), (5, 20, 6), "{name}");
        for (i, t) in ds.trajectories.iter().enumerate() {
            assert_eq!(t.len(), 200, "{name} trajectory {i}");
            // The flag at step 199 is the 200-step time limit, never a real termination.
            assert!(t.terminated.iter().all(|&f| !f), "{name} trajectory {i} terminated");
            let truncated: Vec<usize> =
                t.truncated.iter().enumerate().filter(|(_, &f)| f).map(|(s, _)| s).collect();
            assert_eq!(truncated, [199], "{name} trajectory {i}");
            assert!(t.actions.iter().all(|a| (-1.0..=1.0).contains(a)), "{name} actions");
        }
        let arrays: Vec<(&str, &str, &[usize])> = loaded
            .arrays
            .iter()
            .map(|a| (a.key.as_str(), a.dtype.as_str(), a.shape.as_slice()))
            .collect();
        assert_eq!(
            arrays,
            [
                ("observations", "float32", &[200, 20][..]),
                ("next_observations", "float32", &[200, 20][..]),
                ("actions", "float32", &[200, 6][..]),
                ("rewards", "float32", &[200, 1][..]),
                ("terminals", "bool", &[200, 1][..]),
            ],
            "{name}"
        );
    }
}

#[test]
fn returns_match_the_readme() {
    let Some(dir) = official_prompts() else { return };
    // The README's figures, rounded to one decimal in the reference notes (cheetah_vel-2:
    // -16.2...-15.7), so each bound is widened by the rounding (0.05).
    let check = |task: &str, lo: f64, hi: f64| {
        let returns = load(&dir, task).returns();
        assert_eq!(returns.len(), 5);
        for r in returns {
            assert!((lo..=hi).contains(&r), "{task}: return {r} outside {lo}..{hi}");
        }
    };
    check("cheetah_dir-0", 630.0, 687.0);
    check("cheetah_dir-1", 1129.0, 1171.0);
    check("cheetah_vel-2", -16.25, -15.65);
    check("cheetah_vel-39", -57.75, -56.55);
}

#[test]
fn returns_match_numpy_exactly() {
    let Some(dir) = official_prompts() else { return };
    // `x['rewards'].astype(np.float64).sum()` for each trajectory, printed to 4 decimals by numpy
    // 2.4 from the same files.
    let numpy: [(&str, [f64; 5]); 4] = [
        ("cheetah_dir-0", [661.0169, 684.8847, 686.7970, 630.4841, 664.7232]),
        ("cheetah_dir-1", [1152.7949, 1152.4157, 1129.4143, 1170.4546, 1160.9727]),
        ("cheetah_vel-2", [-16.2053, -15.9313, -15.8592, -15.7449, -15.6928]),
        ("cheetah_vel-39", [-57.6704, -57.4809, -57.3046, -56.9641, -56.5647]),
    ];
    for (task, want) in numpy {
        let got = load(&dir, task).returns();
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-3, "{task}: {got:?} vs numpy {want:?}");
        }
    }
}

#[test]
fn next_observations_are_the_observations_shifted_by_one() {
    let Some(dir) = official_prompts() else { return };
    // An independent check that the array bytes are decoded in the right order: the file stores
    // each state twice, once as `observations[t + 1]` and once as `next_observations[t]`.
    for path in official_files(&dir).iter().step_by(7) {
        let value = pickle::parse(&fs::read(path).expect("read")).expect("parse");
        let PyValue::List(trajs) = value else { panic!("not a list") };
        for traj in &trajs {
            let get = |k: &str| match traj.get(k) {
                Some(PyValue::NdArray(a)) => a.to_f32_vec().expect("float"),
                other => panic!("{k}: {other:?}"),
            };
            let (obs, next) = (get("observations"), get("next_observations"));
            assert_eq!(obs[20..], next[..199 * 20], "{}", path.display());
        }
    }
}

#[test]
fn terminal_options_change_only_the_flags() {
    let Some(path) = official_prompt("cheetah_vel-2-prompt-expert.pkl") else { return };
    let with =
        |how| load_pickle(&path, &ReferenceOptions { terminals_as: how }).expect("load").dataset;
    let auto = with(TerminalsAs::default());
    let term = with(TerminalsAs::Terminated);
    // A horizon the data does not have: the flag at step 199 is then a real termination.
    let other = with(TerminalsAs::Auto { horizon: 1000 });
    for ds in [&term, &other] {
        for (a, b) in auto.trajectories.iter().zip(&ds.trajectories) {
            assert_eq!(a.observations, b.observations);
            assert_eq!(b.terminated.iter().position(|&f| f), Some(199));
            assert!(b.truncated.iter().all(|&f| !f));
        }
    }
}

#[test]
fn inspect_the_directory() {
    let Some(dir) = official_prompts() else { return };
    let reports = inspect_path(&dir).expect("inspect");
    assert_eq!(reports.len(), 42);
    let names: Vec<String> = reports
        .iter()
        .map(|r| {
            r.path.file_name().expect("name").to_string_lossy().replace("-prompt-expert.pkl", "")
        })
        .collect();
    let mut want = vec!["cheetah_dir-0".to_string(), "cheetah_dir-1".to_string()];
    want.extend((0..40).map(|i| format!("cheetah_vel-{i}")));
    assert_eq!(names, want, "natural order");
    for r in &reports {
        assert_eq!(r.format, "reference-pickle");
        assert_eq!((r.trajectories, r.steps, r.obs_dim, r.act_dim), (5, 1000, 20, 6));
        assert_eq!((r.length_min, r.length_max), (200, 200));
    }
    let dir0 = &reports[0];
    assert!(630.0 <= dir0.return_min && dir0.return_max <= 687.0);
    let table = render_table(&reports);
    let lines: Vec<&str> = table.lines().collect();
    assert_eq!(lines.len(), 42 + 3, "{table}");
    assert_eq!(lines[44], "42 files, 210 trajectories, 42000 steps");
    let first: Vec<&str> = lines[2].split_whitespace().collect();
    assert_eq!(
        first,
        [
            "cheetah_dir-0-prompt-expert.pkl",
            "reference-pickle",
            "5",
            "1000",
            "20",
            "6",
            "200",
            &format!("{:.2}", dir0.return_min),
            &format!("{:.2}", dir0.return_mean),
            &format!("{:.2}", dir0.return_max),
        ]
    );
    // Aligned: every row of the table proper is as wide as the header rule.
    assert!(lines[1..44].iter().all(|l| l.len() == lines[1].len()), "{table}");
    let json = serde_json::to_value(&reports[0]).expect("serialize");
    assert_eq!(json["dtypes"][0]["key"], "observations");
    assert_eq!(json["format"], "reference-pickle");
}

#[test]
fn inspect_reads_native_files_beside_pickles() {
    // One official file and its native conversion in one directory: both are reported, in
    // natural order, with the same contents.
    let Some(src) = official_prompt("cheetah_vel-10-prompt-expert.pkl") else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    fs::copy(&src, dir.path().join("cheetah_vel-10-prompt-expert.pkl")).expect("copy");
    let ds = load_pickle(&src, &ReferenceOptions::default()).expect("load").dataset;
    let meta = native::FileMeta::new("cheetah_vel", 9, "prompt-expert");
    let native_path = dir.path().join("cheetah_vel-9-prompt-expert.safetensors");
    native::write_task_dataset(&native_path, &ds, &meta).expect("write native");

    let reports = inspect_path(dir.path()).expect("inspect");
    let formats: Vec<&str> = reports.iter().map(|r| r.format).collect();
    assert_eq!(formats, ["native", "reference-pickle"], "cheetah_vel-9 sorts before -10");
    let (n, p) = (&reports[0], &reports[1]);
    assert_eq!(
        (n.trajectories, n.steps, n.obs_dim, n.act_dim, n.length_min, n.length_max),
        (p.trajectories, p.steps, p.obs_dim, p.act_dim, p.length_min, p.length_max)
    );
    assert_eq!(
        (n.return_min, n.return_mean, n.return_max),
        (p.return_min, p.return_mean, p.return_max)
    );
    let dtypes: Vec<(&str, &str, &[usize])> =
        n.dtypes.iter().map(|a| (a.key.as_str(), a.dtype.as_str(), a.shape.as_slice())).collect();
    assert_eq!(
        dtypes,
        [
            ("observations", "float32", &[200, 20][..]),
            ("actions", "float32", &[200, 6][..]),
            ("rewards", "float32", &[200][..]),
            ("terminated", "uint8", &[200][..]),
            ("truncated", "uint8", &[200][..]),
        ]
    );
    // A single file works too.
    assert_eq!(inspect_path(&native_path).expect("inspect file"), reports[..1]);
}
