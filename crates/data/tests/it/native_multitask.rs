//! `load_multitask` over directories of native files, reference pickles or both, and
//! `convert_reference_dir`.

#![allow(clippy::unwrap_used)] // in tests a panic is the failure report

use crate::support;

use pdt_testkit::reference::official_prompt;
use std::path::Path;

use pdt_data::multitask::{
    convert_reference_dir, load_multitask, load_task_file, resolve_task_file, DataFormat,
    DatasetSpec,
};
use pdt_data::native::{read_file_meta, read_task_dataset, write_task_dataset, FileMeta};
use pdt_data::{TaskDataset, TaskId};
use support::{sample_dataset, traj};

/// A dataset of task `i` (distinct per task and kind).
fn task_ds(i: usize, prompt: bool, obs_dim: usize) -> TaskDataset {
    let seed = (i * 10 + usize::from(prompt)) as u32;
    let len = if prompt { 4 } else { 9 };
    TaskDataset::new(vec![
        traj(obs_dim, 6, len, seed, false, true),
        traj(obs_dim, 6, 3, seed + 5, true, false),
    ])
    .unwrap()
}

fn write_native(dir: &Path, env: &str, i: usize, mode: &str, ds: &TaskDataset) {
    let path = dir.join(format!("{env}-{i}-{mode}.safetensors"));
    write_task_dataset(&path, ds, &FileMeta::new(env, i, mode)).unwrap();
}

#[test]
fn loads_native_files_in_task_order() {
    let dir = tempfile::tempdir().unwrap();
    for i in [0, 3, 5] {
        write_native(dir.path(), "cheetah_vel", i, "expert", &task_ds(i, false, 20));
        write_native(dir.path(), "cheetah_vel", i, "prompt-expert", &task_ds(i, true, 20));
    }
    let spec = DatasetSpec {
        format: DataFormat::Native,
        ..DatasetSpec::new(dir.path(), "cheetah_vel", vec![5, 0])
    };
    let mt = load_multitask(&spec).unwrap();
    assert_eq!((mt.obs_dim, mt.act_dim), (20, 6));
    let ids: Vec<String> = mt.tasks.iter().map(|t| t.id.to_string()).collect();
    assert_eq!(ids, ["cheetah_vel-5", "cheetah_vel-0"]);
    let t5 = mt.task(&TaskId { env: "cheetah_vel".into(), index: 5 }).unwrap();
    assert_eq!(t5.dataset, task_ds(5, false, 20));
    assert_eq!(t5.prompts, task_ds(5, true, 20));
}

#[test]
fn modes_select_the_files() {
    let dir = tempfile::tempdir().unwrap();
    write_native(dir.path(), "cheetah_vel", 1, "medium", &task_ds(1, false, 20));
    write_native(dir.path(), "cheetah_vel", 1, "expert", &task_ds(7, false, 20));
    write_native(dir.path(), "cheetah_vel", 1, "prompt-random", &task_ds(1, true, 20));
    let spec = DatasetSpec {
        dataset_mode: "medium".into(),
        prompt_mode: "random".into(),
        ..DatasetSpec::new(dir.path(), "cheetah_vel", vec![1])
    };
    let mt = load_multitask(&spec).unwrap();
    assert_eq!(mt.tasks[0].dataset, task_ds(1, false, 20));
    assert_eq!(mt.tasks[0].prompts, task_ds(1, true, 20));
}

#[test]
fn missing_file_lists_the_paths_tried() {
    let dir = tempfile::tempdir().unwrap();
    write_native(dir.path(), "ant_dir", 0, "expert", &task_ds(0, false, 27));
    let spec = DatasetSpec::new(dir.path(), "ant_dir", vec![0]);
    let msg = load_multitask(&spec).unwrap_err().to_string();
    for part in [
        "task ant_dir-0",
        "ant_dir-0-prompt-expert.safetensors",
        "ant_dir-0-prompt-expert.pkl",
        "tried",
    ] {
        assert!(msg.contains(part), "{part:?} not in {msg}");
    }
    let e = resolve_task_file(dir.path(), "ant_dir", 0, "prompt-expert", DataFormat::Native)
        .unwrap_err()
        .to_string();
    assert!(e.contains(".safetensors") && !e.contains(".pkl"), "{e}");
    let e = resolve_task_file(dir.path(), "ant_dir", 0, "expert", DataFormat::ReferencePickle)
        .unwrap_err()
        .to_string();
    assert!(e.contains("ant_dir-0-expert.pkl") && !e.contains(".safetensors"), "{e}");
}

#[test]
fn tasks_with_different_dims_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    for (i, obs_dim) in [(0, 20), (1, 17)] {
        write_native(dir.path(), "e", i, "expert", &task_ds(i, false, obs_dim));
        write_native(dir.path(), "e", i, "prompt-expert", &task_ds(i, true, obs_dim));
    }
    let msg =
        load_multitask(&DatasetSpec::new(dir.path(), "e", vec![0, 1])).unwrap_err().to_string();
    // the file at fault is named first, with the file that fixed the dims
    assert!(msg.starts_with(&format!("{}", dir.path().join("e-1-expert").display())), "{msg}");
    assert!(msg.contains("dims 17/") && msg.contains("e-0-expert") && msg.contains("20/"), "{msg}");
    let msg = load_multitask(&DatasetSpec::new(dir.path(), "e", vec![])).unwrap_err().to_string();
    assert!(msg.contains("no tasks"), "{msg}");
}

#[test]
fn a_broken_file_is_named_in_the_error() {
    let dir = tempfile::tempdir().unwrap();
    write_native(dir.path(), "e", 0, "expert", &task_ds(0, false, 20));
    std::fs::write(dir.path().join("e-0-prompt-expert.safetensors"), b"garbage!garbage").unwrap();
    let msg = load_multitask(&DatasetSpec::new(dir.path(), "e", vec![0])).unwrap_err().to_string();
    assert!(msg.contains("e-0-prompt-expert.safetensors"), "{msg}");
}

#[test]
fn data_format_names() {
    for f in [DataFormat::Native, DataFormat::ReferencePickle, DataFormat::Auto] {
        assert_eq!(f.to_string().parse::<DataFormat>().unwrap(), f);
        let json = serde_json::to_string(&f).unwrap();
        assert_eq!(json, format!("\"{f}\""));
    }
    assert_eq!("pkl".parse::<DataFormat>().unwrap(), DataFormat::ReferencePickle);
    assert!("hdf5".parse::<DataFormat>().is_err());
    assert_eq!(DataFormat::default(), DataFormat::Auto);
}

/// A directory mixing a native D_i and the official pickled P_i; Auto prefers .safetensors when
/// both exist.
#[test]
fn mixes_native_files_and_reference_pickles() {
    let Some(pkl) = official_prompt("cheetah_vel-2-prompt-expert.pkl") else { return };
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(&pkl, dir.path().join("cheetah_vel-2-prompt-expert.pkl")).unwrap();
    write_native(dir.path(), "cheetah_vel", 2, "expert", &task_ds(2, false, 20));

    let mt = load_multitask(&DatasetSpec::new(dir.path(), "cheetah_vel", vec![2])).unwrap();
    let prompts = &mt.tasks[0].prompts;
    assert_eq!((prompts.obs_dim, prompts.act_dim, prompts.trajectories.len()), (20, 6, 5));
    assert!(prompts.trajectories.iter().all(|t| t.len() == 200));
    for r in prompts.returns() {
        assert!((-16.5..-15.5).contains(&r), "cheetah_vel-2 prompt return {r}");
    }
    assert_eq!(mt.tasks[0].dataset, task_ds(2, false, 20));
    let from_pickle = prompts.clone();

    // Pickle only -> the native D_i is not found.
    let spec = DatasetSpec {
        format: DataFormat::ReferencePickle,
        ..DatasetSpec::new(dir.path(), "cheetah_vel", vec![2])
    };
    assert!(load_multitask(&spec).unwrap_err().to_string().contains("cheetah_vel-2-expert.pkl"));

    // A native P_i next to the pickle wins under Auto.
    let native_prompts = task_ds(2, true, 20);
    write_native(dir.path(), "cheetah_vel", 2, "prompt-expert", &native_prompts);
    let mt = load_multitask(&DatasetSpec::new(dir.path(), "cheetah_vel", vec![2])).unwrap();
    assert_eq!(mt.tasks[0].prompts, native_prompts);
    assert_ne!(mt.tasks[0].prompts, from_pickle);
}

#[test]
fn converts_reference_pickles() {
    let (Some(a), Some(b)) = (
        official_prompt("cheetah_vel-2-prompt-expert.pkl"),
        official_prompt("cheetah_dir-1-prompt-expert.pkl"),
    ) else {
        return;
    };
    let src = tempfile::tempdir().unwrap();
    for p in [&a, &b] {
        std::fs::copy(p, src.path().join(p.file_name().unwrap())).unwrap();
    }
    std::fs::write(src.path().join("notes.txt"), b"ignored").unwrap();
    let dst = src.path().join("native"); // created by the conversion
    let converted = convert_reference_dir(src.path(), &dst).unwrap();
    assert_eq!(converted.len(), 2);
    // Name order: cheetah_dir before cheetah_vel.
    assert_eq!(converted[0].meta, FileMeta::new("cheetah_dir", 1, "prompt-expert"));
    assert_eq!(converted[1].meta, FileMeta::new("cheetah_vel", 2, "prompt-expert"));
    for c in &converted {
        assert_eq!((c.trajectories, c.steps, c.obs_dim, c.act_dim), (5, 1000, 20, 6));
        assert_eq!(c.dest.parent().unwrap(), dst);
        assert_eq!(c.dest.file_stem(), c.source.file_stem());
        assert_eq!(read_file_meta(&c.dest).unwrap(), c.meta);
        // Same trajectories as the pickle reader gives.
        assert_eq!(read_task_dataset(&c.dest).unwrap(), load_task_file(&c.source).unwrap());
    }
    // The converted directory loads natively.
    let spec = DatasetSpec {
        format: DataFormat::Native,
        ..DatasetSpec::new(&dst, "cheetah_dir", vec![1])
    };
    let e = load_multitask(&spec).unwrap_err().to_string();
    assert!(e.contains("cheetah_dir-1-expert.safetensors"), "{e}"); // only prompts were converted
    let p = resolve_task_file(&dst, "cheetah_dir", 1, "prompt-expert", DataFormat::Native).unwrap();
    let r = load_task_file(&p).unwrap().returns();
    assert!(r.iter().all(|r| (1129.0..1171.0).contains(r)), "{r:?}");

    let empty = tempfile::tempdir().unwrap();
    let msg = convert_reference_dir(empty.path(), &dst).unwrap_err().to_string();
    assert!(msg.contains("no .pkl files"), "{msg}");
}

#[test]
fn load_task_file_rejects_unknown_extensions() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x-0-expert.hdf5");
    std::fs::write(&p, b"").unwrap();
    let msg = load_task_file(&p).unwrap_err().to_string();
    assert!(msg.contains("x-0-expert.hdf5") && msg.contains("unknown file type"), "{msg}");
    let _ = sample_dataset(1, 1);
}
