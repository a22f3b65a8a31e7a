//! `evaluate_through`: an evaluation whose forwards another computation makes (a pack's batched
//! model) takes exactly the evaluator's own actions when that computation is the same model's
//! full forward, and an actor's wrong answer is an error naming the shapes, not a panic.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_envs::EnvFamily;
use pdt_eval::{
    evaluate, evaluate_through, ActRows, EvalError, EvalReturns, EvalSettings, EvalTask, Inference,
};
use pdt_model::{PromptDt, PromptDtConfig, Segments};
use pdt_prompt::{SegmentBatch, StateNorm};
use std::cell::Cell;
use tch::{nn::VarStore, Device, Tensor};

const K: usize = 6;

fn prompt_for(i: usize) -> SegmentBatch {
    let steps = 4;
    SegmentBatch {
        batch: 1,
        steps,
        state_dim: 2,
        act_dim: 2,
        states: (0..steps * 2).map(|j| 0.1 * (i + j) as f32).collect(),
        actions: vec![0.05 * i as f32; steps * 2],
        returns_to_go: (0..steps).map(|t| -0.1 * (steps - t) as f32).collect(),
        timesteps: (3..3 + steps as i64).collect(),
        mask: vec![1.0; steps],
    }
}

/// Three tasks of 4 episodes each (the tasks' prompts differ, so a row given another task's
/// prompt would act differently).
fn tasks(family: &dyn EnvFamily, with_prompt: bool) -> Vec<EvalTask> {
    [3usize, 11, 29]
        .iter()
        .map(|&i| EvalTask {
            name: format!("point_robot-{i}"),
            index: i,
            envs: (0..4).map(|_| family.make(i).unwrap()).collect(),
            seeds: (10..14).collect(),
            prompt: with_prompt.then(|| prompt_for(i)),
        })
        .collect()
}

fn settings(inference: Inference) -> EvalSettings {
    EvalSettings {
        k: K,
        horizon: 15,
        rtg_scale: 10.0,
        target_return: 0.0,
        returns: EvalReturns::Decreasing,
        norm: StateNorm { mean: vec![0.1, 0.3], std: vec![0.5, 0.4] },
        max_batch: 5, // three windows of episodes, the last one short
        device: Device::Cpu,
        env_threads: 1,
        inference,
    }
}

/// The model's full forward, as a pack's engine computes it for one run, counting its calls.
struct Same<'m> {
    model: &'m PromptDt,
    calls: Cell<usize>,
}

impl ActRows for Same<'_> {
    fn act_rows(&self, history: &Segments, prompt: Option<&Segments>) -> Result<Tensor, EvalError> {
        self.calls.set(self.calls.get() + 1);
        let preds = tch::no_grad(|| self.model.forward(history, prompt, false)); // [A, K, da]
        Ok(preds.select(1, K as i64 - 1))
    }
}

/// An actor that answers with one action too few.
struct Short;

impl ActRows for Short {
    fn act_rows(&self, history: &Segments, _: Option<&Segments>) -> Result<Tensor, EvalError> {
        Ok(Tensor::zeros([history.batch_size() - 1, 2], (tch::Kind::Float, Device::Cpu)))
    }
}

#[test]
fn an_actor_computing_the_full_forward_takes_the_evaluators_own_actions() {
    let _torch = pdt_testkit::process::libtorch(); // seeds the process's generator
    tch::set_num_threads(1);
    tch::manual_seed(3);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    let family = pdt_envs::family("point_robot").unwrap();
    for with_prompt in [true, false] {
        let own = evaluate(&model, tasks(family.as_ref(), with_prompt), &settings(Inference::Full))
            .unwrap();
        let actor = Same { model: &model, calls: Cell::new(0) };
        // The evaluator's own inference setting does not matter: the actor computes.
        let through = evaluate_through(
            &model,
            tasks(family.as_ref(), with_prompt),
            &settings(Inference::Cached),
            &actor,
        )
        .unwrap();
        assert_eq!(own.len(), 12);
        assert_eq!(own, through, "prompt {with_prompt}");
        for (a, b) in own.iter().zip(&through) {
            let same = a.actions.iter().zip(&b.actions).all(|(x, y)| x.to_bits() == y.to_bits());
            assert!(same && a.actions.len() == b.actions.len(), "prompt {with_prompt}");
        }
        // One call per environment step of each of the three windows (15 steps each).
        assert_eq!(actor.calls.get(), 45, "prompt {with_prompt}");
    }
}

#[test]
fn an_actor_with_the_wrong_number_of_actions_is_an_error() {
    let _torch = pdt_testkit::process::libtorch(); // seeds the process's generator
    tch::manual_seed(3);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    let family = pdt_envs::family("point_robot").unwrap();
    let e =
        evaluate_through(&model, tasks(family.as_ref(), true), &settings(Inference::Full), &Short)
            .unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, EvalError::Acting(_)), "{msg}");
    assert!(msg.contains("[4, 2] actions for 5 episodes of 2"), "{msg}");
}
