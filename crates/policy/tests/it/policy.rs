//! The policy runtime that `promptdt serve` and the Python `Policy` act through: episodes stepped
//! with it take the evaluator's actions, and every input either front end would pass on is
//! checked here, once (observation, reward, target return, prompt arrays, `max_ep_len`,
//! return-to-go overflow), a refused step leaving its episode as it was.
#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use pdt_eval::{evaluate, EvalTask};
use pdt_policy::{Episode, Policy, PolicyError, PromptArrays};

use crate::support;
use support::tiny_run::tiny_run;

fn policy() -> Policy {
    Policy::load(&tiny_run().1, None, None).unwrap()
}

fn err<T: std::fmt::Debug>(r: Result<T, PolicyError>) -> String {
    r.unwrap_err().to_string()
}

/// One episode of point-robot task `task` from reset seed `seed`, stepped as the Python `Policy`
/// and the server step theirs; returns its actions.
fn stepped_episode(p: &Policy, task: usize, seed: u64, prompt_seed: u64) -> Vec<f32> {
    let family = pdt_envs::family("point_robot").unwrap();
    let mut env = family.make(task).unwrap();
    let obs: Vec<f64> = env.reset(seed).iter().map(|&x| f64::from(x)).collect();
    let prompt = p.task_prompt(task, prompt_seed).unwrap();
    let prefix = p.prefix(&[&prompt]).unwrap();
    let mut e = p.start(p.observation(&obs).unwrap(), p.target(None).unwrap());
    let mut actions = Vec::new();
    loop {
        let a = p.act(&[&e], Some(&prefix));
        e.accept(&a).unwrap();
        actions.extend_from_slice(&a);
        let step = env.step(&a).unwrap();
        if step.terminated || step.truncated {
            return actions;
        }
        let obs: Vec<f64> = step.obs.iter().map(|&x| f64::from(x)).collect();
        let s = p.step(f64::from(step.reward), p.observation(&obs).unwrap()).unwrap();
        p.record(&mut e, s).unwrap();
    }
}

#[test]
fn an_episode_takes_the_evaluators_actions() {
    tch::set_num_threads(1);
    let p = policy();
    for (task, seed, prompt_seed) in [(34usize, 5u64, 0u64), (2, 9, 3)] {
        let stepped = stepped_episode(&p, task, seed, prompt_seed);
        let settings = p.eval_settings();
        let t = EvalTask {
            name: format!("point_robot-{task}"),
            index: task,
            envs: vec![pdt_envs::family("point_robot").unwrap().make(task).unwrap()],
            seeds: vec![seed],
            prompt: Some(p.task_prompt(task, prompt_seed).unwrap()),
            target_return: None,
        };
        let evaluated = evaluate(&p.model, vec![t], &settings).unwrap().remove(0).actions;
        assert_eq!(stepped.len(), 40);
        let same = stepped.iter().zip(&evaluated).all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same, "task {task}: stepped {stepped:?}\nevaluated {evaluated:?}");
    }
}

#[test]
fn bad_inputs_are_refused_naming_the_field() {
    let p = policy();
    // target return
    assert!(err(p.target(Some(f64::NAN))).contains("target_return NaN is not a finite number"));
    assert!(err(p.target(Some(1e31))).contains("target_return 1e31 is outside the accepted range"));
    assert!(p.target(Some(1e30)).is_ok());
    // observation
    assert!(err(p.observation(&[0.0])).contains("observation has 1 values, the policy takes 2"));
    assert!(err(p.observation(&[0.0, 1e39])).contains("observation[1] = 1e39 is not a finite f32"));
    // reward
    let obs = || p.observation(&[0.1, 0.0]).unwrap();
    assert!(err(p.step(f64::INFINITY, obs())).contains("reward inf is not a finite number"));
    assert!(err(p.step(-1e31, obs())).contains("reward -1e31 is outside the accepted range"));
    // prompt arrays
    let arrays = |rtg: f64, t: i64| PromptArrays {
        states: vec![vec![0.0, 0.0]],
        actions: vec![vec![0.1, 0.1]],
        returns_to_go: vec![rtg],
        timesteps: vec![t],
    };
    let mut inputs = pdt_policy::Inputs::default();
    let e = err(p.prompt_from_arrays(&arrays(1e31, 0), &mut inputs));
    assert!(e.contains("prompt.returns_to_go[0] = 1e31 is outside the accepted range"), "{e}");
    let e = err(p.prompt_from_arrays(&arrays(1.0, 5000), &mut inputs));
    assert!(e.contains("prompt.timesteps: 5000 is outside [0, 1000)"), "{e}");
    assert!(p.prompt_from_arrays(&arrays(1.0, 3), &mut inputs).is_ok());
    // a task the run does not have
    assert!(err(p.task_prompt(999, 0)).contains("task 999 is not one of the run's tasks"));
}

/// The state of an episode that a refused step must leave as it was.
fn state(e: &Episode) -> (usize, f64, Vec<f32>, Vec<f32>, Vec<f32>) {
    let h = e.history();
    (h.t, h.ret, h.states.clone(), h.actions.clone(), h.rtg.clone())
}

#[test]
fn returns_to_go_that_overflow_and_episodes_past_max_ep_len_are_refused() {
    let p = policy();
    let obs = || p.observation(&[0.1, 0.0]).unwrap();
    // Rewards each within range add up beyond it: the target 1e30 less a reward of -1e30.
    let mut e = p.start(obs(), p.target(Some(1e30)).unwrap());
    e.accept(&[0.1, 0.1]).unwrap();
    let before = state(&e);
    let step = p.step(-1e30, obs()).unwrap();
    let why = err(p.check(&e, &step));
    assert!(why.contains("would take the episode's return-to-go"), "{why}");
    assert!(err(p.record(&mut e, step)).contains("return-to-go"));
    assert_eq!(state(&e), before);
    // The model's timestep table ends at max_ep_len: the step that would reach it is refused.
    let mut e = p.start(obs(), p.target(None).unwrap());
    for _ in 0..p.max_ep_len() - 1 {
        e.accept(&[0.0, 0.0]).unwrap();
        p.record(&mut e, p.step(0.0, obs()).unwrap()).unwrap();
    }
    let full = p.record(&mut e, p.step(0.0, obs()).unwrap()).unwrap_err();
    assert!(matches!(full, PolicyError::EpisodeFull { max_ep_len: 1000 }), "{full}");
    assert_eq!(e.t(), p.max_ep_len() - 1);
}

#[test]
fn an_action_that_is_not_finite_takes_its_step_back() {
    let p = policy();
    let mut e = p.start(p.observation(&[0.1, 0.0]).unwrap(), p.target(None).unwrap());
    e.accept(&[0.2, -0.1]).unwrap();
    let before = state(&e);
    p.record(&mut e, p.step(-0.5, p.observation(&[3e5, 0.0]).unwrap()).unwrap()).unwrap();
    assert_eq!(e.t(), 1);
    let why = e.accept(&[f32::NAN, 0.0]).unwrap_err().to_string();
    assert!(why.contains("not finite") && why.contains("observation[0] = 3e5"), "{why}");
    assert_eq!(state(&e), before);
    // The episode goes on from where it was: the same step again, now with its last action.
    p.record(&mut e, p.step(-0.5, p.observation(&[0.1, 0.0]).unwrap()).unwrap()).unwrap();
    assert_eq!(&e.history().actions[..], &[0.2, -0.1]);
}
