//! Write -> read round trips of the native format, its metadata, naming convention and card.

#![allow(clippy::unwrap_used)] // in tests a panic is the failure report

use crate::support;

use pdt_data::native::{
    parse_task_file_stem, read_card, read_file_meta, read_task_dataset, task_file_stem, write_card,
    write_task_dataset, CardFile, CardTask, DatasetCard, FileMeta, ReturnStats,
};
use pdt_data::{DataError, TaskDataset, Trajectory};
use proptest::prelude::*;
use safetensors::tensor::Dtype;
use support::{sample_dataset, traj};

#[test]
fn roundtrip_preserves_every_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cheetah_vel-2-expert.safetensors");
    let ds = sample_dataset(20, 6);
    write_task_dataset(&path, &ds, &FileMeta::new("cheetah_vel", 2, "expert")).unwrap();
    let back = read_task_dataset(&path).unwrap();
    assert_eq!(back, ds);
    assert_eq!(back.returns(), ds.returns());
}

/// The reader decodes the floats through 1 MiB buffers: a file of several buffers, whose episodes
/// (odd lengths, odd widths) straddle the buffer boundaries, reads back exactly.
#[test]
fn roundtrip_across_read_buffer_boundaries() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big-0-expert.safetensors");
    let lens = [1usize, 333, 4097, 77, 2049, 1, 5003];
    let ds = TaskDataset::new(
        (0..40).map(|i| traj(37, 5, lens[i % lens.len()], i as u32, i % 3 == 0, true)).collect(),
    )
    .unwrap();
    write_task_dataset(&path, &ds, &FileMeta::default()).unwrap();
    // Observations alone span several 1 MiB buffers.
    assert!(ds.num_steps() * 37 * 4 > 3 << 20, "{} steps", ds.num_steps());
    assert_eq!(read_task_dataset(&path).unwrap(), ds);
}

#[test]
fn roundtrip_of_minimal_dataset() {
    // One episode of one step, obs_dim = act_dim = 1, no metadata at all.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiny.safetensors");
    let ds = TaskDataset::new(vec![traj(1, 1, 1, 9, false, false)]).unwrap();
    write_task_dataset(&path, &ds, &FileMeta::default()).unwrap();
    assert_eq!(read_task_dataset(&path).unwrap(), ds);
    assert_eq!(read_file_meta(&path).unwrap(), FileMeta::default());
}

#[test]
fn roundtrip_keeps_special_float_values_bit_exact() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.safetensors");
    let obs = vec![-0.0, f32::MIN_POSITIVE / 2.0, f32::MAX, f32::MIN, 1e-45, 0.1];
    let t = Trajectory::new(
        2,
        1,
        obs.clone(),
        vec![0.5, -0.5, 1.0],
        vec![f32::EPSILON, -1e30, 3.0],
        vec![false; 3],
        vec![false, false, true],
    )
    .unwrap();
    let ds = TaskDataset::new(vec![t]).unwrap();
    write_task_dataset(&path, &ds, &FileMeta::default()).unwrap();
    let back = read_task_dataset(&path).unwrap();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&back.trajectories[0].observations), bits(&obs));
    assert_eq!(back, ds);
}

#[test]
fn file_meta_roundtrips_and_is_read_from_the_header_only() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ML1-pick-place-v2-11-prompt-expert.safetensors");
    let meta = FileMeta::new("ML1-pick-place-v2", 11, "prompt-expert");
    write_task_dataset(&path, &sample_dataset(3, 2), &meta).unwrap();
    assert_eq!(read_file_meta(&path).unwrap(), meta);

    let partial = FileMeta { env: Some("ant_dir".into()), task_index: None, mode: None };
    write_task_dataset(&path, &sample_dataset(3, 2), &partial).unwrap();
    assert_eq!(read_file_meta(&path).unwrap(), partial);
}

/// The file is plain safetensors with the documented names, dtypes, shapes and metadata.
#[test]
fn file_layout_is_the_documented_one() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cheetah_dir-1-expert.safetensors");
    let ds = sample_dataset(5, 3);
    write_task_dataset(&path, &ds, &FileMeta::new("cheetah_dir", 1, "expert")).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let meta = header.metadata().clone().unwrap();
    assert_eq!(meta["format"], "promptdt-trajectories");
    assert_eq!(meta["format_version"], "1");
    assert_eq!(meta["env"], "cheetah_dir");
    assert_eq!(meta["task_index"], "1");
    assert_eq!(meta["mode"], "expert");
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let n = ds.num_steps();
    for (name, dtype, shape) in [
        ("observations", Dtype::F32, vec![n, 5]),
        ("actions", Dtype::F32, vec![n, 3]),
        ("rewards", Dtype::F32, vec![n]),
        ("terminated", Dtype::U8, vec![n]),
        ("truncated", Dtype::U8, vec![n]),
        ("episode_starts", Dtype::I64, vec![5]),
    ] {
        let t = st.tensor(name).unwrap();
        assert_eq!((t.dtype(), t.shape().to_vec()), (dtype, shape), "{name}");
    }
    assert_eq!(st.len(), 6);
    let starts: Vec<i64> = st
        .tensor("episode_starts")
        .unwrap()
        .data()
        .chunks_exact(8)
        .map(|c| i64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert_eq!(starts, vec![0, 7, 8, 20, 25]);
    assert_eq!(st.tensor("terminated").unwrap().data()[7], 1);
    assert_eq!(st.tensor("truncated").unwrap().data()[6], 1);
}

/// A file hand-built by another writer (e.g. Python) with bool flags, no metadata and an extra
/// tensor is readable.
#[test]
fn reads_files_from_other_writers() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("from-python.safetensors");
    let ds = sample_dataset(4, 2);
    let mut tensors = support::tensors_of(&ds);
    for t in &mut tensors {
        if t.name == "terminated" || t.name == "truncated" {
            t.dtype = Dtype::BOOL;
        }
    }
    tensors.push(support::RawTensor::f32("next_observations", vec![1, 1], &[0.0]));
    std::fs::write(&path, support::safetensors_bytes(&tensors, None)).unwrap();
    assert_eq!(read_task_dataset(&path).unwrap(), ds);
    assert_eq!(read_file_meta(&path).unwrap(), FileMeta::default());
}

#[test]
fn file_name_convention() {
    assert_eq!(task_file_stem("cheetah_vel", 2, "prompt-expert"), "cheetah_vel-2-prompt-expert");
    let p = |s: &str| parse_task_file_stem(s);
    assert_eq!(p("cheetah_vel-2-expert"), Some(("cheetah_vel".into(), 2, "expert".into())));
    assert_eq!(
        p("cheetah_vel-39-prompt-expert"),
        Some(("cheetah_vel".into(), 39, "prompt-expert".into()))
    );
    assert_eq!(
        p("ML1-pick-place-v2-11-prompt-expert"),
        Some(("ML1-pick-place-v2".into(), 11, "prompt-expert".into()))
    );
    assert_eq!(p("expert"), None);
    assert_eq!(p("cheetah_vel-expert"), None);
    assert_eq!(p("3-expert"), None);
    assert_eq!(p("cheetah_vel-3"), None);
    assert_eq!(p("cheetah_vel--expert"), None);
    let meta = FileMeta::from_file_name(std::path::Path::new("/d/ant_dir-7-medium.pkl")).unwrap();
    assert_eq!(meta, FileMeta::new("ant_dir", 7, "medium"));
    assert_eq!(meta.file_name().as_deref(), Some("ant_dir-7-medium.safetensors"));
    assert_eq!(FileMeta::default().file_name(), None);
}

#[test]
fn writer_rejects_what_the_reader_would_reject() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.safetensors");
    let meta = FileMeta::default();

    let mut ds = sample_dataset(3, 2);
    ds.trajectories[2].observations[4] = f32::NAN;
    let e = write_task_dataset(&path, &ds, &meta).unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("episode 2") && msg.contains("observations"), "{msg}");
    assert!(msg.contains("step 1, component 1") && msg.contains("NaN"), "{msg}");

    let mut ds = sample_dataset(3, 2);
    ds.trajectories[0].terminated[3] = true;
    let msg = write_task_dataset(&path, &ds, &meta).unwrap_err().to_string();
    assert!(msg.contains("`terminated` is set at step 3") && msg.contains("last step"), "{msg}");

    let mut ds = sample_dataset(3, 2);
    ds.trajectories[1].actions.pop();
    let msg = write_task_dataset(&path, &ds, &meta).unwrap_err().to_string();
    assert!(msg.contains("episode 1") && msg.contains("`actions`"), "{msg}");

    let ds = TaskDataset { obs_dim: 3, act_dim: 2, trajectories: vec![] };
    let e = write_task_dataset(&path, &ds, &meta).unwrap_err();
    assert!(matches!(&e, DataError::InFile { source, .. } if matches!(**source, DataError::Empty)));

    assert!(!path.exists(), "nothing may be written for an invalid dataset");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "no temp file left behind");
}

#[test]
fn dataset_card_roundtrip() {
    let dir = tempfile::tempdir().unwrap();
    assert_eq!(read_card(dir.path()).unwrap(), None);
    let ds = sample_dataset(20, 6);
    let card = DatasetCard {
        format: "promptdt-dataset".into(),
        format_version: "1".into(),
        env: "cheetah_vel".into(),
        obs_dim: 20,
        act_dim: 6,
        tasks: vec![CardTask {
            index: 2,
            params: serde_json::json!({"target_velocity": 0.225}),
            files: vec![CardFile::describe("cheetah_vel-2-expert.safetensors", "expert", &ds)],
        }],
        generator: serde_json::json!({"policy": "sac", "seed": 0}),
    };
    write_card(dir.path(), &card).unwrap();
    assert_eq!(read_card(dir.path()).unwrap(), Some(card.clone()));
    let f = &card.tasks[0].files[0];
    assert_eq!((f.episodes, f.steps), (4, 25));
    let r = ds.returns();
    assert!((f.returns.mean - r.iter().sum::<f64>() / 4.0).abs() < 1e-12);
    assert_eq!(f.returns.max, r.iter().copied().fold(f64::MIN, f64::max));

    // Minimal hand-written card with an unknown key: defaults fill in, extra keys are ignored.
    let text = r#"{"env": "ant_dir", "obs_dim": 27, "act_dim": 8, "tasks": [], "future": 1}"#;
    std::fs::write(dir.path().join("dataset.json"), text).unwrap();
    let card = read_card(dir.path()).unwrap().unwrap();
    assert_eq!((card.format.as_str(), card.format_version.as_str()), ("promptdt-dataset", "1"));
    assert!(card.generator.is_null());

    std::fs::write(dir.path().join("dataset.json"), r#"{"env": 3}"#).unwrap();
    let msg = read_card(dir.path()).unwrap_err().to_string();
    assert!(msg.contains("dataset.json") && msg.contains("invalid dataset card"), "{msg}");
}

#[test]
fn return_stats_match_numpy_conventions() {
    let s = ReturnStats::of(&[1.0, 2.0, 3.0, 4.0]);
    assert_eq!((s.mean, s.min, s.max), (2.5, 1.0, 4.0));
    assert!((s.std - 1.25f64.sqrt()).abs() < 1e-15); // population std, like np.std
    assert_eq!(ReturnStats::of(&[]), ReturnStats { mean: 0.0, std: 0.0, min: 0.0, max: 0.0 });
}

fn arb_dataset() -> impl Strategy<Value = TaskDataset> {
    (1usize..5, 1usize..4, prop::collection::vec((1usize..9, any::<u8>()), 1..6)).prop_flat_map(
        |(obs_dim, act_dim, eps)| {
            let trajs: Vec<_> = eps
                .into_iter()
                .map(|(len, flags)| {
                    (
                        prop::collection::vec(-1e6f32..1e6, len * obs_dim),
                        prop::collection::vec(-1f32..1.0, len * act_dim),
                        prop::collection::vec(-1e3f32..1e3, len),
                    )
                        .prop_map(move |(o, a, r)| {
                            let mut term = vec![false; len];
                            let mut trunc = vec![false; len];
                            term[len - 1] = flags & 1 == 1;
                            trunc[len - 1] = flags & 2 == 2;
                            Trajectory::new(obs_dim, act_dim, o, a, r, term, trunc).unwrap()
                        })
                })
                .collect();
            trajs.prop_map(|t| TaskDataset::new(t).unwrap())
        },
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn roundtrip_random_datasets(ds in arb_dataset()) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.safetensors");
        write_task_dataset(&path, &ds, &FileMeta::new("e", 0, "m")).unwrap();
        prop_assert_eq!(read_task_dataset(&path).unwrap(), ds);
    }
}

/// Load speed, run by hand (not a timed test):
/// `cargo test --release -p pdt-data --test it native_roundtrip:: -- --ignored --nocapture`.
/// 1000 episodes x 200 steps = 200k steps, obs_dim 20, act_dim 6 (the size of a cheetah expert
/// set).
#[test]
#[ignore]
fn load_speed_200k_steps() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cheetah_vel-0-expert.safetensors");
    let ds =
        TaskDataset::new((0..1000).map(|i| traj(20, 6, 200, i, false, true)).collect()).unwrap();
    let t0 = std::time::Instant::now();
    write_task_dataset(&path, &ds, &FileMeta::new("cheetah_vel", 0, "expert")).unwrap();
    let write = t0.elapsed();
    let size = std::fs::metadata(&path).unwrap().len();
    let mut best = std::time::Duration::MAX;
    for _ in 0..10 {
        let t = std::time::Instant::now();
        let back = read_task_dataset(&path).unwrap();
        best = best.min(t.elapsed());
        assert_eq!(back.num_steps(), 200_000);
    }
    let mut best_raw = std::time::Duration::MAX;
    for _ in 0..10 {
        let t = std::time::Instant::now();
        let bytes = std::fs::read(&path).unwrap();
        best_raw = best_raw.min(t.elapsed());
        assert_eq!(bytes.len() as u64, size);
    }
    eprintln!(
        "file {:.1} MB; write {:.1} ms; read_task_dataset best of 10 {:.2} ms ({:.2} GB/s); \
         plain std::fs::read of the same file {:.2} ms",
        size as f64 / 1e6,
        write.as_secs_f64() * 1e3,
        best.as_secs_f64() * 1e3,
        size as f64 / best.as_secs_f64() / 1e9,
        best_raw.as_secs_f64() * 1e3,
    );
}
