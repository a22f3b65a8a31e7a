//! Prompts chosen per episode at its reset (`evaluate_with`, the `nearest-start` strategy's path):
//! each episode acts with the prompt chosen from its own first observation, batched with the
//! others, as it would alone with that prompt as its task's.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_eval::{
    evaluate, evaluate_with, EpisodePrompts, EvalError, EvalReturns, EvalSettings, EvalTask,
};
use pdt_model::{PromptDt, PromptDtConfig};
use pdt_prompt::{SegmentBatch, StateNorm};
use pdt_rundir::config::Inference;
use tch::{nn::VarStore, Device};

/// A 4-step prompt made from a start observation (so episodes with other starts get other
/// prompts).
fn prompt_from(obs: &[f32]) -> SegmentBatch {
    let steps = 4;
    SegmentBatch {
        batch: 1,
        steps,
        state_dim: 2,
        act_dim: 2,
        states: (0..steps)
            .flat_map(|t| [obs[0] + t as f32 * 0.1, obs[1] - t as f32 * 0.1])
            .collect(),
        actions: vec![0.05; steps * 2],
        returns_to_go: (0..steps).map(|t| -0.1 * (steps - t) as f32).collect(),
        timesteps: (3..3 + steps as i64).collect(),
        mask: vec![1.0; steps],
    }
}

/// A prompt per episode from its first observation (the point robot starts every episode at
/// the origin, so the task and episode shift it: every episode gets its own); records what it
/// was asked and gave, in order.
#[derive(Default)]
struct FromStart {
    seen: Vec<(usize, usize, Vec<f32>, SegmentBatch)>,
}

impl EpisodePrompts for FromStart {
    fn at_reset(
        &mut self,
        task: usize,
        episode: usize,
        obs: &[f32],
    ) -> Result<SegmentBatch, EvalError> {
        let shifted = [obs[0] + task as f32, obs[1] + 0.3 * episode as f32];
        let p = prompt_from(&shifted);
        self.seen.push((task, episode, obs.to_vec(), p.clone()));
        Ok(p)
    }
}

fn settings(inference: Inference, max_batch: usize) -> EvalSettings {
    EvalSettings {
        k: 6,
        horizon: 15,
        rtg_scale: 10.0,
        target_return: 0.0,
        returns: EvalReturns::Decreasing,
        norm: StateNorm { mean: vec![0.1, 0.3], std: vec![0.5, 0.4] },
        max_batch,
        device: Device::Cpu,
        env_threads: 1,
        inference,
    }
}

fn task(i: usize, seeds: &[u64], prompt: Option<SegmentBatch>) -> EvalTask {
    let family = pdt_envs::family("point_robot").unwrap();
    EvalTask {
        name: format!("point_robot-{i}"),
        index: i,
        envs: seeds.iter().map(|_| family.make(i).unwrap()).collect(),
        seeds: seeds.to_vec(),
        prompt,
        target_return: None,
    }
}

#[test]
fn each_episode_acts_with_the_prompt_of_its_own_start() {
    let _torch = pdt_testkit::process::libtorch(); // seeds the process's generator
    tch::set_num_threads(1);
    tch::manual_seed(3);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    let (tasks, seeds) = ([2usize, 18], [0u64, 1, 2]);
    for (inference, max_batch) in
        [(Inference::Full, 4096), (Inference::Cached, 4096), (Inference::Full, 2)]
    {
        let mut chooser = FromStart::default();
        let batched = evaluate_with(
            &model,
            tasks.iter().map(|&i| task(i, &seeds, None)).collect(),
            &settings(inference, max_batch),
            Some(&mut chooser),
        )
        .unwrap();
        // asked once per episode, in (task, episode) order, with its first observation
        let order: Vec<(usize, usize)> = chooser.seen.iter().map(|s| (s.0, s.1)).collect();
        assert_eq!(order, vec![(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]);
        // the point robot's first observation: its start at the origin
        assert!(chooser.seen.iter().all(|s| s.2 == vec![0.0, 0.0]), "{:?}", chooser.seen);
        for (k, (t, e, _, prompt)) in chooser.seen.iter().enumerate() {
            // The same episode alone, its prompt given as its task's.
            let alone = evaluate(
                &model,
                vec![task(tasks[*t], &seeds[*e..*e + 1], Some(prompt.clone()))],
                &settings(inference, 1),
            )
            .unwrap();
            let (a, b) = (&batched[k].actions, &alone[0].actions);
            if k > 0 {
                // another prompt, other actions: the episode's own prompt is the one used
                assert_ne!(a, &batched[k - 1].actions);
            }
            assert_eq!(a.len(), b.len());
            let diff = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
            // Batched and alone differ at most by kernel rounding (bit for bit on batch-invariant
            // CPUs with the full forward).
            if inference == Inference::Full && pdt_testkit::cpu::batch_invariant() {
                assert_eq!(diff, 0.0, "{inference:?} task {t} episode {e}");
            } else {
                assert!(diff < 1e-5, "{inference:?} task {t} episode {e}: {diff:e}");
            }
        }
    }
}

#[test]
fn prompts_of_different_lengths_in_one_batch_are_refused() {
    struct Uneven;
    impl EpisodePrompts for Uneven {
        fn at_reset(
            &mut self,
            _: usize,
            episode: usize,
            obs: &[f32],
        ) -> Result<SegmentBatch, EvalError> {
            let mut p = prompt_from(obs);
            if episode == 1 {
                p.steps = 3;
                p.states.truncate(6);
                p.actions.truncate(6);
                p.returns_to_go.truncate(3);
                p.timesteps.truncate(3);
                p.mask.truncate(3);
            }
            Ok(p)
        }
    }
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    let e = evaluate_with(
        &model,
        vec![task(2, &[0, 1], None)],
        &settings(Inference::Cached, 8),
        Some(&mut Uneven),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("4 and 3 steps"), "{e}");
}

/// A task's own target return (a suite's `[[tasks]] target_return`, `EvalTask::target_return`)
/// is what its episodes are conditioned on: batched with a task on the settings' G*, each acts as
/// it would alone with its G* as the settings' own.
#[test]
fn a_tasks_own_target_return_conditions_its_episodes() {
    let _torch = pdt_testkit::process::libtorch();
    tch::set_num_threads(1);
    tch::manual_seed(5);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    let prompt = prompt_from(&[0.2, -0.1]);
    let with_target = |target: Option<f32>| EvalTask {
        target_return: target,
        ..task(4, &[7], Some(prompt.clone()))
    };
    let cfg = settings(Inference::Full, 4096);
    let both = evaluate(&model, vec![with_target(Some(-30.0)), with_target(None)], &cfg).unwrap();
    let alone = |g: f32| {
        let cfg = EvalSettings { target_return: g, ..cfg.clone() };
        evaluate(&model, vec![with_target(None)], &cfg).unwrap().remove(0).actions
    };
    let close = |a: &[f32], b: &[f32]| {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5)
    };
    assert!(close(&both[0].actions, &alone(-30.0)), "the task's own G* conditions it");
    assert!(close(&both[1].actions, &alone(cfg.target_return)), "the other keeps the run's");
    // The return token matters to the model: the two targets give other actions.
    assert_ne!(both[0].actions, both[1].actions);
}
