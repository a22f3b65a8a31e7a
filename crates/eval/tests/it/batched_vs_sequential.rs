//! The batched evaluation (all episodes of all tasks in one forward per step) takes exactly the
//! actions of the reference's one-episode-at-a-time loop (`max_batch = 1`).
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_envs::EnvFamily;
use pdt_eval::{evaluate, EvalReturns, EvalSettings, EvalTask};
use pdt_model::{PromptDt, PromptDtConfig};
use pdt_prompt::{SegmentBatch, StateNorm};
use pdt_rundir::config::Inference;
use tch::{nn::VarStore, Device};

fn prompt_for(goal: [f32; 2]) -> SegmentBatch {
    // A 5-step prompt that walks toward the goal, as a demonstration's tail would.
    let steps = 5;
    let states: Vec<f32> =
        (0..steps).flat_map(|t| [goal[0] * (t as f32) / 5.0, goal[1] * (t as f32) / 5.0]).collect();
    SegmentBatch {
        batch: 1,
        steps,
        state_dim: 2,
        act_dim: 2,
        states,
        actions: vec![0.05; steps * 2],
        returns_to_go: (0..steps).map(|t| -0.1 * (steps - t) as f32).collect(),
        timesteps: (14..14 + steps as i64).collect(),
        mask: vec![1.0; steps],
    }
}

fn tasks(family: &dyn EnvFamily, with_prompt: bool) -> Vec<EvalTask> {
    [2usize, 10, 18, 26, 34]
        .iter()
        .map(|&i| {
            let goal = pdt_envs::point_robot::goal(i).unwrap();
            EvalTask {
                name: format!("point_robot-{i}"),
                index: i,
                envs: (0..7).map(|_| family.make(i).unwrap()).collect(),
                seeds: (0..7).collect(),
                prompt: with_prompt.then(|| prompt_for(goal)),
                target_return: None,
            }
        })
        .collect()
}

#[test]
fn batched_evaluation_takes_exactly_the_sequential_actions() {
    // Bitwise equality holds with one libtorch thread. With several, libtorch splits some
    // reductions according to the batch size, so batched and single-episode forwards can differ in
    // the last bit (seen with 2 threads); the rollouts are then equal up to float rounding.
    let _torch = pdt_testkit::process::libtorch(); // seeds the process's generator
    tch::set_num_threads(1);
    tch::manual_seed(7);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    let family = pdt_envs::family("point_robot").unwrap();
    for (with_prompt, returns) in [(true, EvalReturns::Decreasing), (false, EvalReturns::Constant)]
    {
        let settings = |max_batch| EvalSettings {
            k: 10,
            horizon: 20,
            rtg_scale: 10.0,
            target_return: 0.0,
            returns,
            norm: StateNorm { mean: vec![0.1, 0.3], std: vec![0.5, 0.4] },
            max_batch,
            device: Device::Cpu,
            env_threads: max_batch.min(3),
            // The reference's forward: batched and one-at-a-time take the same kernels.
            inference: Inference::Full,
        };
        let batched =
            evaluate(&model, tasks(family.as_ref(), with_prompt), &settings(4096)).unwrap();
        let sequential =
            evaluate(&model, tasks(family.as_ref(), with_prompt), &settings(1)).unwrap();
        assert_eq!(batched.len(), 35);
        for (b, s) in batched.iter().zip(&sequential) {
            assert_eq!((b.task_index, b.seed, b.length), (s.task_index, s.seed, s.length));
            assert_eq!(b.actions.len(), 40);
            let same = b.actions.iter().zip(&s.actions).all(|(x, y)| x.to_bits() == y.to_bits());
            let diff =
                b.actions.iter().zip(&s.actions).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
            // Bit for bit where the CPU's kernels are batch-invariant (AVX2), within
            // BATCH_TOLERANCE elsewhere (AVX-512; pdt_testkit::cpu::batch_invariant).
            if pdt_testkit::cpu::batch_invariant() {
                assert!(
                    same,
                    "task {} seed {}: batched actions differ by up to {diff:e}",
                    b.task_index, b.seed
                );
                assert_eq!(b.episode_return.to_bits(), s.episode_return.to_bits());
            } else {
                assert!(
                    diff <= pdt_testkit::cpu::BATCH_TOLERANCE,
                    "task {} seed {}: batched actions differ by up to {diff:e}",
                    b.task_index,
                    b.seed
                );
                assert!((b.episode_return - s.episode_return).abs() <= 1e-4);
            }
        }
        // The episodes of different tasks behave differently (the prompt carries the goal).
        if with_prompt {
            assert_ne!(batched[0].actions, batched[7 * 4].actions);
        }
    }
}

/// The cached path (`Inference::Cached`: prompt keys and values once per task, last layer for
/// the last state token) takes the full forward's actions within float rounding, batched or not.
#[test]
fn cached_inference_takes_the_full_forwards_actions() {
    let _torch = pdt_testkit::process::libtorch(); // seeds the process's generator
    tch::set_num_threads(1);
    tch::manual_seed(7);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    let family = pdt_envs::family("point_robot").unwrap();
    for with_prompt in [true, false] {
        let settings = |max_batch, inference| EvalSettings {
            k: 10,
            horizon: 20,
            rtg_scale: 10.0,
            target_return: 0.0,
            returns: EvalReturns::Decreasing,
            norm: StateNorm { mean: vec![0.1, 0.3], std: vec![0.5, 0.4] },
            max_batch,
            device: Device::Cpu,
            env_threads: 1,
            inference,
        };
        let full =
            evaluate(&model, tasks(family.as_ref(), with_prompt), &settings(4096, Inference::Full))
                .unwrap();
        for max_batch in [4096, 1] {
            let cached = evaluate(
                &model,
                tasks(family.as_ref(), with_prompt),
                &settings(max_batch, Inference::Cached),
            )
            .unwrap();
            let mut worst = 0f32;
            for (f, c) in full.iter().zip(&cached) {
                assert_eq!((f.task_index, f.seed, f.length), (c.task_index, c.seed, c.length));
                for (x, y) in f.actions.iter().zip(&c.actions) {
                    worst = worst.max((x - y).abs());
                }
                assert!((f.episode_return - c.episode_return).abs() < 1e-4);
            }
            assert!(worst < 1e-5, "prompt {with_prompt} batch {max_batch}: {worst:e}");
        }
    }
}
