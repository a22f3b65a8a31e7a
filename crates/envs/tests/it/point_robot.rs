//! Point-robot family and scripted collection: policies' quality ordering, determinism of the
//! written files, and that the files load with pdt-data's readers.

use std::collections::BTreeMap;
use std::time::Instant;

use pdt_data::mode::{Mode, Set};
use pdt_data::multitask::{load_multitask, DatasetSpec};
use pdt_data::native::{self, read_card, read_file_meta, read_task_dataset, FileMeta};
use pdt_data::TaskDataset;
use pdt_envs::collect_scripted::{
    collect, episode_rng, generate_for, CollectConfig, CollectError, ScriptedFamily,
};
use pdt_envs::point_robot::{
    self, run_episode, PointRobotFamily, DEFAULT_TEST_TASKS, HORIZON, OOD_TEST_TASKS,
};
use pdt_envs::{family, EnvError, EnvFamily};

use crate::support;
use support::dir_bytes;

/// The point robot's collection defaults (every goal and mode, 100 + 5 episodes, seed 0).
fn defaults() -> CollectConfig {
    let scripted = PointRobotFamily::default().scripted().expect("the point robot is scripted");
    CollectConfig::for_family(scripted)
}

fn small_config(seed: u64) -> CollectConfig {
    CollectConfig {
        seed,
        episodes_per_task: 10,
        prompt_episodes: 3,
        modes: Mode::ALL.to_vec(),
        tasks: vec![0, 2, 39],
        ..defaults()
    }
}

/// `episodes` point-robot episodes of `(task, mode)` for one set, with `seed`.
fn generate(
    seed: u64,
    task: usize,
    mode: Mode,
    set: Set,
    episodes: usize,
) -> Result<TaskDataset, CollectError> {
    Ok(generate_for(&CollectConfig { seed, ..defaults() }, task, mode, set, episodes)?.0)
}

fn no_progress() -> impl FnMut(usize, usize) {
    |_, _| {}
}

#[test]
fn registry_finds_the_family() {
    let fam = family("point_robot").expect("family");
    assert_eq!(fam.name(), "point_robot");
    assert_eq!(fam.split_names()[0], "default");
    assert!(matches!(family("nope"), Err(EnvError::UnknownEnv(..))));
}

#[test]
fn expert_beats_medium_beats_random_on_test_tasks() {
    let dir = tempfile::tempdir().expect("tempdir");
    let tasks: Vec<usize> = DEFAULT_TEST_TASKS.iter().chain(&OOD_TEST_TASKS).copied().collect();
    let cfg = CollectConfig { seed: 7, tasks: tasks.clone(), ..defaults() };
    let summary = collect(&cfg, dir.path(), &mut no_progress()).expect("collect");
    let mean = |m: Mode, t: &[usize]| summary.mean_return(m, t).expect("collected");
    for (split, t) in [("default", &DEFAULT_TEST_TASKS[..]), ("ood", &OOD_TEST_TASKS[..])] {
        let (e, m, r) = (mean(Mode::Expert, t), mean(Mode::Medium, t), mean(Mode::Random, t));
        println!("{split} test tasks {t:?}: expert {e:.3}, medium {m:.3}, random {r:.3}");
        // "Clear margin": at least 2 return units (one fifth of rtg_scale) between neighbours.
        assert!(e > m + 2.0, "expert {e} vs medium {m}");
        assert!(m > r + 2.0, "medium {m} vs random {r}");
    }
    for entry in &summary.entries {
        println!(
            "task {:2} {:6}: D mean {:8.3} std {:6.3} | P mean {:8.3} std {:6.3}",
            entry.task,
            entry.mode,
            entry.dataset.mean,
            entry.dataset.std,
            entry.prompts.mean,
            entry.prompts.std
        );
    }
}

#[test]
fn expert_reaches_the_goal_and_episodes_are_truncated() {
    for task in [0, 17, 39] {
        let traj = run_episode(
            task,
            Mode::Expert,
            &mut episode_rng(1, task, Mode::Expert, Set::Dataset, 0),
        )
        .expect("episode");
        assert_eq!(traj.len(), HORIZON);
        assert!(traj.terminated.iter().all(|&t| !t));
        assert_eq!(traj.truncated.iter().filter(|&&t| t).count(), 1);
        assert_eq!(traj.truncated.last(), Some(&true));
        // Starts at the origin; every action respects the speed limit.
        assert_eq!(traj.obs(0), &[0.0, 0.0]);
        assert!(traj.actions.iter().all(|a| a.abs() <= point_robot::MAX_SPEED));
        // After 20 steps at up to 0.1 per coordinate the unit-distance goal is reached.
        assert!(traj.rewards[HORIZON - 1] > -0.05, "final reward {}", traj.rewards[HORIZON - 1]);
    }
}

#[test]
fn recorded_episodes_replay_exactly_in_the_env() {
    // Observations are the state before each action and rewards come from the env, so replaying
    // the recorded actions must reproduce both exactly.
    let fam = PointRobotFamily::default();
    for mode in Mode::ALL {
        let ds = generate(3, 21, mode, Set::Dataset, 4).expect("generate");
        for traj in &ds.trajectories {
            let mut env = fam.make(21).expect("make");
            let mut obs = env.reset(99);
            for t in 0..traj.len() {
                assert_eq!(obs, traj.obs(t));
                let step = env.step(traj.action(t)).expect("step");
                assert_eq!(step.reward, traj.rewards[t]);
                assert_eq!(step.truncated, traj.truncated[t]);
                obs = step.obs;
            }
        }
    }
}

#[test]
fn episodes_do_not_depend_on_other_episodes_or_the_set_size() {
    let a = generate(5, 4, Mode::Medium, Set::Dataset, 3).expect("generate");
    let b = generate(5, 4, Mode::Medium, Set::Dataset, 8).expect("generate");
    assert_eq!(a.trajectories[..], b.trajectories[..3]);
    // The prompt set uses a different stream from the main set.
    let p = generate(5, 4, Mode::Medium, Set::Prompt, 3).expect("generate");
    assert_ne!(a.trajectories, p.trajectories);
    // Expert demonstrations are not all identical (action noise).
    let e = generate(5, 4, Mode::Expert, Set::Dataset, 2).expect("generate");
    assert_ne!(e.trajectories[0].actions, e.trajectories[1].actions);
}

/// A safetensors file's parts: the header JSON (parsed, so key order does not matter) and the
/// bytes after the header.
fn split_safetensors(bytes: &[u8]) -> (serde_json::Value, &[u8]) {
    let len = u64::from_le_bytes(bytes[..8].try_into().expect("8-byte prefix")) as usize;
    let header = serde_json::from_slice(&bytes[8..8 + len]).expect("header JSON");
    (header, &bytes[8 + len..])
}

/// Collects `small_config(seed)` into a fresh directory; returns the directory's files.
fn collect_files(seed: u64) -> BTreeMap<String, Vec<u8>> {
    let dir = tempfile::tempdir().expect("tempdir");
    collect(&small_config(seed), dir.path(), &mut no_progress()).expect("collect");
    dir_bytes(dir.path())
}

#[test]
fn same_seed_gives_identical_data_and_different_seeds_differ() {
    let (b1, b2, b3) = (collect_files(11), collect_files(11), collect_files(12));
    // 3 tasks x 3 modes x (D_i, P_i) + the card; no temporary files left behind.
    assert_eq!(b1.len(), 3 * 3 * 2 + 1, "{:?}", b1.keys().collect::<Vec<_>>());
    assert_eq!(b1.keys().collect::<Vec<_>>(), b2.keys().collect::<Vec<_>>());
    assert_eq!(b1.keys().collect::<Vec<_>>(), b3.keys().collect::<Vec<_>>());
    for (name, bytes) in &b1 {
        let other = &b2[name];
        if name == "dataset.json" {
            assert!(bytes == other, "{name} differs between two runs with one seed");
            assert!(bytes != &b3[name], "{name} is the same for seeds 11 and 12");
            continue;
        }
        // Same length, same header content, and the tensor data byte for byte. Only the order of
        // the header's `__metadata__` keys may differ (see the ignored test below).
        assert_eq!(bytes.len(), other.len(), "{name}: lengths differ");
        let ((h1, d1), (h2, d2)) = (split_safetensors(bytes), split_safetensors(other));
        assert_eq!(h1, h2, "{name}: headers differ");
        assert!(d1 == d2, "{name}: tensor data differs between two runs with one seed");
        let (_, d3) = split_safetensors(&b3[name]);
        assert!(d1 != d3, "{name}: tensor data is the same for seeds 11 and 12");
    }
}

/// Whole files byte for byte (pdt-data writes the safetensors header with sorted keys).
#[test]
fn same_seed_gives_byte_identical_files() {
    let (b1, b2) = (collect_files(11), collect_files(11));
    for (name, bytes) in &b1 {
        assert!(bytes == &b2[name], "{name} differs between two runs with one seed");
    }
}

#[test]
fn written_files_load_back() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = small_config(21);
    let mut calls = Vec::new();
    let summary =
        collect(&cfg, dir.path(), &mut |done, total| calls.push((done, total))).expect("collect");
    assert_eq!(calls, (1..=9).map(|d| (d, 9)).collect::<Vec<_>>());

    // Each file by itself, with its metadata.
    for entry in &summary.entries {
        let ds = read_task_dataset(&entry.dataset_file).expect("read D_i");
        assert_eq!((ds.obs_dim, ds.act_dim), (2, 2));
        assert_eq!(ds.trajectories.len(), cfg.episodes_per_task);
        assert_eq!(ds.num_steps(), cfg.episodes_per_task * HORIZON);
        assert_eq!(native::ReturnStats::of(&ds.returns()), entry.dataset);
        assert_eq!(
            read_file_meta(&entry.dataset_file).expect("meta"),
            FileMeta::new("point_robot", entry.task, entry.mode.name())
        );
        let p = read_task_dataset(&entry.prompt_file).expect("read P_i");
        assert_eq!(p.trajectories.len(), cfg.prompt_episodes);
        assert_eq!(
            read_file_meta(&entry.prompt_file).expect("meta"),
            FileMeta::new("point_robot", entry.task, format!("prompt-{}", entry.mode))
        );
    }

    // Through the multi-task loader, for every mode.
    for mode in Mode::ALL {
        let mut spec = DatasetSpec::new(dir.path(), "point_robot", cfg.tasks.clone());
        spec.dataset_mode = mode.name().into();
        spec.prompt_mode = mode.name().into();
        let mt = load_multitask(&spec).expect("load_multitask");
        assert_eq!((mt.obs_dim, mt.act_dim), (2, 2));
        assert_eq!(mt.tasks.len(), 3);
        for (t, &index) in mt.tasks.iter().zip(&cfg.tasks) {
            assert_eq!(t.id.index, index);
            assert_eq!(t.dataset.trajectories.len(), cfg.episodes_per_task);
            assert_eq!(t.prompts.trajectories.len(), cfg.prompt_episodes);
        }
    }

    // The card lists every file with the same statistics.
    let card = read_card(dir.path()).expect("read card").expect("card present");
    assert_eq!(card.env, "point_robot");
    assert_eq!((card.obs_dim, card.act_dim), (2, 2));
    assert_eq!(card.tasks.iter().map(|t| t.index).collect::<Vec<_>>(), cfg.tasks);
    let fam = PointRobotFamily::default();
    for task in &card.tasks {
        assert_eq!(task.params, fam.task_params(task.index).expect("params"));
        assert_eq!(task.files.len(), 6);
        for f in &task.files {
            assert!(dir.path().join(&f.name).is_file(), "{}", f.name);
            let ds = read_task_dataset(&dir.path().join(&f.name)).expect("read");
            // JSON keeps f64s to within an ulp or so (serde_json's default float parser).
            let want = native::ReturnStats::of(&ds.returns());
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs().max(1.0);
            assert!(
                close(f.returns.mean, want.mean)
                    && close(f.returns.std, want.std)
                    && close(f.returns.min, want.min)
                    && close(f.returns.max, want.max),
                "{}: card {:?} vs file {want:?}",
                f.name,
                f.returns
            );
            assert_eq!(f.steps, ds.num_steps());
        }
    }
    assert_eq!(card.generator["seed"], 21);
    assert_eq!(card.generator["episodes_per_task"], 10);
    assert!(card.generator["policies"]["medium"].is_string());
}

#[test]
fn full_collection_is_fast() {
    let dir = tempfile::tempdir().expect("tempdir");
    let start = Instant::now();
    let summary = collect(&defaults(), dir.path(), &mut no_progress()).expect("collect");
    let elapsed = start.elapsed();
    println!("40 tasks x 3 modes x (100 + 5) episodes: {elapsed:?}");
    assert_eq!(summary.entries.len(), 40 * 3);
    // Generous bound: debug builds and slow disks (each file is fsynced) must still pass.
    assert!(elapsed.as_secs_f64() < 10.0, "took {elapsed:?}");
}

#[test]
fn config_errors() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bad = |cfg: CollectConfig| collect(&cfg, dir.path(), &mut no_progress()).map(|_| ());
    let base = small_config(0);
    assert!(matches!(
        bad(CollectConfig { tasks: vec![3, 40], ..base.clone() }),
        Err(CollectError::Env(EnvError::UnknownTask { task: 40, .. }))
    ));
    for cfg in [
        CollectConfig { episodes_per_task: 0, ..base.clone() },
        CollectConfig { prompt_episodes: 0, ..base.clone() },
        CollectConfig { modes: vec![], ..base.clone() },
        CollectConfig { tasks: vec![], ..base.clone() },
        CollectConfig { tasks: vec![1, 1], ..base.clone() },
        CollectConfig { modes: vec![Mode::Random, Mode::Random], ..base.clone() },
        CollectConfig { reach_action_noise: f64::NAN, ..base.clone() },
        CollectConfig { reach_action_noise: -0.1, ..base.clone() },
    ] {
        assert!(matches!(bad(cfg.clone()), Err(CollectError::Config(_))), "{cfg:?}");
    }
    // Nothing was written for refused configs.
    assert_eq!(std::fs::read_dir(dir.path()).expect("read_dir").count(), 0);
    assert_eq!("medium".parse::<Mode>().expect("mode"), Mode::Medium);
    assert!("best".parse::<Mode>().is_err());
}

#[test]
fn write_errors_name_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    // A directory where a data file should go makes that one write fail.
    let blocker = dir.path().join("point_robot-2-prompt-medium.safetensors");
    std::fs::create_dir(&blocker).expect("mkdir");
    let err = collect(&small_config(0), dir.path(), &mut no_progress()).expect_err("must fail");
    match &err {
        CollectError::Write { path, .. } => assert_eq!(path, &blocker),
        other => panic!("expected a write error, got {other:?}"),
    }
    assert!(err.to_string().contains("point_robot-2-prompt-medium.safetensors"), "{err}");

    // An output "directory" that is a file.
    let file = dir.path().join("plain-file");
    std::fs::write(&file, b"x").expect("write");
    let err = collect(&small_config(0), &file.join("sub"), &mut no_progress()).expect_err("fail");
    assert!(matches!(err, CollectError::CreateDir { .. }), "{err:?}");
}

#[test]
fn an_interrupted_collection_writes_no_card_and_names_the_stop() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = small_config(0);
    cfg.interrupt.set();
    let err = collect(&cfg, tmp.path(), &mut no_progress()).unwrap_err();
    assert!(matches!(err, CollectError::Interrupted), "{err}");
    assert!(err.to_string().contains("interrupted"), "{err}");
    assert!(!tmp.path().join(native::CARD_FILE_NAME).exists());
    // The flag is no setting: a configuration with it set equals one without.
    assert_eq!(cfg, small_config(0));
    assert!(collect(&small_config(0), tmp.path(), &mut no_progress()).is_ok());
}

#[test]
fn check_dims_names_the_family_and_both_sizes() {
    assert!(pdt_envs::check_dims("point_robot", 2, 2).is_ok());
    let e = pdt_envs::check_dims("cheetah_vel", 3, 1).unwrap_err();
    assert_eq!(
        e.to_string(),
        "data of obs_dim 3 and act_dim 1 cannot be cheetah_vel's: cheetah_vel has obs_dim 20 and \
         act_dim 6"
    );
    let e = pdt_envs::check_dims("nonsense_family", 2, 2).unwrap_err();
    assert!(matches!(e, EnvError::UnknownEnv(..)), "{e}");
}

#[test]
fn scripted_families_are_found_and_serialised_by_name() {
    let names: Vec<&str> = ScriptedFamily::all().iter().map(|f| f.name()).collect();
    assert_eq!(names, ["point_robot", "metaworld_reach", "dial"]);
    let pr = ScriptedFamily::from_name("point-robot").expect("the alias");
    assert_eq!(pr, defaults().family);
    assert_ne!(pr, ScriptedFamily::from_name("dial").expect("dial"));
    // A family collected by an RL agent has none; the error names the ones that do.
    assert!(ScriptedFamily::from_name("cheetah_dir").is_none());
    let err = ScriptedFamily::named("cheetah_dir").expect_err("not scripted").to_string();
    assert!(err.contains("`cheetah_dir`") && err.contains("point_robot, metaworld_reach, dial"));
    // A config round-trips through its name.
    let cfg = small_config(3);
    let json = serde_json::to_string(&cfg).expect("serialise");
    assert!(json.contains(r#""family":"point_robot""#), "{json}");
    let back: CollectConfig = serde_json::from_str(&json).expect("deserialise");
    assert_eq!(back, cfg);
    let bad = serde_json::from_str::<ScriptedFamily>(r#""ant_dir""#).expect_err("not scripted");
    assert!(bad.to_string().contains("`ant_dir` has no scripted policies"), "{bad}");
}
