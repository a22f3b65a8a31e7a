//! Meta-World reach data collection: the scripted expert succeeds in every episode, the three
//! policies are ordered, the recorded observations are ML1's (goal hidden), the reward rule that
//! `promptdt data report` uses for success agrees with the environment's flag, and the same
//! configuration gives the same bytes.

use pdt_data::mode::Mode;
use pdt_data::native;
use pdt_envs::collect_scripted::{collect, CollectConfig, CollectError, ScriptedFamily};
use pdt_envs::metaworld_reach::{
    MetaWorldReachFamily, ENV_NAME, HORIZON, OBS_DIM, REACH_ACTION_NOISE, SUCCESS_REWARD,
};
use pdt_envs::{EnvError, EnvFamily};

use crate::support;
use support::dir_bytes;

fn reach() -> ScriptedFamily {
    MetaWorldReachFamily::default().scripted().expect("reach is scripted")
}

fn config(seed: u64) -> CollectConfig {
    CollectConfig {
        seed,
        episodes_per_task: 4,
        prompt_episodes: 2,
        modes: Mode::ALL.to_vec(),
        // A training task and a test task of the paper's split.
        tasks: vec![1, 6],
        reach_action_noise: 0.2,
        ..CollectConfig::for_family(reach())
    }
}

#[test]
fn reach_collection_expert_succeeds_and_data_are_ml1_observations() {
    let dir = tempfile::tempdir().expect("tempdir");
    let summary = collect(&config(3), dir.path(), &mut |_, _| {}).expect("collect");
    assert_eq!(summary.entries.len(), 6);

    let card = native::read_card(dir.path()).expect("card").expect("card present");
    assert_eq!((card.env.as_str(), card.obs_dim, card.act_dim), (ENV_NAME, 39, 4));
    assert_eq!(card.tasks[0].params["goal"][0], 0.034093502035680456);

    for &task in &[1, 6] {
        let stat = |m: Mode| summary.get(task, m).expect("collected");
        let (e, m, r) = (stat(Mode::Expert), stat(Mode::Medium), stat(Mode::Random));
        println!(
            "task {task}: expert {:.1} ({:?}), medium {:.1} ({:?}), random {:.1} ({:?})",
            e.dataset.mean,
            e.success_rate,
            m.dataset.mean,
            m.success_rate,
            r.dataset.mean,
            r.success_rate
        );
        // The scripted expert (with Meta-World's harness noise) succeeds in every episode.
        assert_eq!(e.success_rate, Some(1.0));
        assert!(e.dataset.min > 4700.0, "expert return {:?}", e.dataset);
        assert!(e.dataset.mean > m.dataset.mean && m.dataset.mean > r.dataset.mean);

        for mode in Mode::ALL {
            let entry = stat(mode);
            let ds = native::read_task_dataset(&entry.dataset_file).expect("read");
            assert_eq!(ds.trajectories.len(), 4);
            let mut wins = 0;
            for t in &ds.trajectories {
                assert_eq!(t.len(), HORIZON);
                assert!(t.truncated[HORIZON - 1] && !t.terminated.iter().any(|&d| d));
                // ML1 observations: the goal slot is zeroed in every recorded step.
                for row in t.observations.chunks_exact(OBS_DIM) {
                    assert_eq!(&row[36..39], &[0.0, 0.0, 0.0]);
                }
                wins += usize::from(t.rewards.iter().any(|&x| x >= SUCCESS_REWARD));
            }
            // The reward rule of the data report agrees with the environment's success flag.
            assert_eq!(Some(wins as f64 / 4.0), entry.success_rate, "task {task} {mode}");
        }
        // The noise makes the expert's episodes differ.
        let ds = native::read_task_dataset(&e.dataset_file).expect("read");
        assert_ne!(ds.trajectories[0].actions, ds.trajectories[1].actions);
    }
}

#[test]
fn reach_collection_is_deterministic_and_seeded() {
    let (a, b, c) = (tempfile::tempdir(), tempfile::tempdir(), tempfile::tempdir());
    let (a, b, c) = (a.expect("tempdir"), b.expect("tempdir"), c.expect("tempdir"));
    let mut cfg = config(5);
    cfg.episodes_per_task = 2;
    cfg.modes = vec![Mode::Expert, Mode::Random];
    collect(&cfg, a.path(), &mut |_, _| {}).expect("collect");
    collect(&cfg, b.path(), &mut |_, _| {}).expect("collect");
    assert_eq!(dir_bytes(a.path()), dir_bytes(b.path()));
    cfg.seed = 6;
    collect(&cfg, c.path(), &mut |_, _| {}).expect("collect");
    let (x, y) = (dir_bytes(a.path()), dir_bytes(c.path()));
    assert_ne!(
        x["metaworld_reach-1-expert.safetensors"],
        y["metaworld_reach-1-expert.safetensors"]
    );
}

#[test]
fn reach_collection_refuses_unknown_tasks() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cfg = config(0);
    cfg.tasks = vec![1, 50];
    match collect(&cfg, dir.path(), &mut |_, _| {}) {
        Err(CollectError::Env(EnvError::UnknownTask { env, task: 50, n: 50 })) => {
            assert_eq!(env, ENV_NAME)
        }
        other => panic!("expected an unknown task, got {other:?}"),
    }
    // Nothing was written.
    assert!(dir_bytes(dir.path()).is_empty());
    // The family defaults: the paper's 20 tasks, 200 episodes.
    let d = CollectConfig::for_family(reach());
    assert_eq!(d.tasks, (1..=20).collect::<Vec<_>>());
    assert_eq!(d.episodes_per_task, 200);
    assert_eq!(d.reach_action_noise, REACH_ACTION_NOISE);
}

#[test]
fn reach_without_noise_repeats_the_deterministic_expert() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cfg = config(0);
    cfg.episodes_per_task = 3;
    cfg.modes = vec![Mode::Expert];
    cfg.tasks = vec![1];
    cfg.reach_action_noise = 0.0;
    let summary = collect(&cfg, dir.path(), &mut |_, _| {}).expect("collect");
    let e = summary.get(1, Mode::Expert).expect("collected");
    assert_eq!(e.success_rate, Some(1.0));
    let ds = native::read_task_dataset(&e.dataset_file).expect("read");
    // Every episode is the same: Meta-World's deterministic expert on a frozen task.
    assert_eq!(ds.trajectories[0], ds.trajectories[1]);
    assert_eq!(ds.trajectories[0], ds.trajectories[2]);
    // Its first action is SawyerReachV3Policy's: 5 (goal - hand), gripper 0.
    let a = &ds.trajectories[0].actions[..4];
    assert_eq!(a[3], 0.0);
    let card = native::read_card(dir.path()).expect("card").expect("card present");
    assert_eq!(card.generator["action_noise_std"], 0.0);
}
