//! `VecEnv`'s worker pool: masked steps and partial resets against environments stepped alone, for
//! any thread count; thread counts capped by the environment count; dropping; panics in an
//! environment reaching the caller; refused inputs.

use std::panic::{self, AssertUnwindSafe};

use pdt_envs::vec_env::VecEnv;
use pdt_envs::{family, Env, EnvError, StepResult};

fn ok<T>(r: Result<T, EnvError>) -> T {
    r.unwrap_or_else(|e| panic!("{e}"))
}

/// Environments of different families and action sizes (6 and 8).
fn mixed() -> Vec<Box<dyn Env>> {
    [("cheetah_vel", 12), ("ant_dir", 7), ("cheetah_dir", 1), ("ant_dir", 30), ("cheetah_vel", 3)]
        .into_iter()
        .map(|(name, task)| ok(ok(family(name)).make(task)))
        .collect()
}

/// A deterministic action value in [-1, 1].
fn value(t: usize, i: usize, j: usize) -> f32 {
    ((t * 7 + i * 5 + j * 3) as f32 * 0.37).sin()
}

#[test]
fn masked_steps_and_partial_resets_match_environments_stepped_alone() {
    let mut alone = mixed();
    let seeds = [11u64, 12, 13, 14, 15];
    let first: Vec<Vec<f32>> = alone.iter_mut().zip(seeds).map(|(e, s)| e.reset(s)).collect();
    // Environment i is stepped at step t unless (t + i) % 3 == 0; at t = 10, environments 3 and 0
    // (in that order) start a new episode.
    let stepped = |t: usize, i: usize| !(t + i).is_multiple_of(3);
    let mut expected: Vec<Vec<Option<StepResult>>> = Vec::new();
    let mut second_first = Vec::new();
    for t in 0..20 {
        if t == 10 {
            second_first = vec![alone[3].reset(99), alone[0].reset(98)];
        }
        let row = (alone.iter_mut().enumerate())
            .map(|(i, e)| {
                let a: Vec<f32> = (0..e.act_dim()).map(|j| value(t, i, j)).collect();
                stepped(t, i).then(|| ok(e.step(&a)))
            })
            .collect();
        expected.push(row);
    }

    for threads in [0, 1, 2, 3, 5, 8] {
        let mut venv = VecEnv::new(mixed(), threads);
        assert_eq!(venv.threads(), threads.clamp(1, 5));
        let acts = venv.dims().iter().map(|d| d.act_dim).collect::<Vec<_>>();
        assert_eq!(acts, [6, 8, 6, 8, 6]);
        assert_eq!(venv.flat_action_len(), 34);
        assert_eq!((venv.action_range(1), venv.action_range(5)), (Some(6..14), None));
        assert_eq!(ok(venv.reset(&seeds)), first, "{threads} threads");
        let mut flat = vec![f32::NAN; venv.flat_action_len()];
        for (t, want) in expected.iter().enumerate() {
            if t == 10 {
                assert_eq!(ok(venv.reset_some(&[(3, 99), (0, 98)])), second_first);
            }
            let mask: Vec<bool> = (0..5).map(|i| stepped(t, i)).collect();
            for (i, &on) in mask.iter().enumerate() {
                let Some(range) = venv.action_range(i) else { panic!("no range for {i}") };
                for (j, x) in flat[range].iter_mut().enumerate() {
                    // Masked-out slots keep a NaN, which an environment would refuse: so they
                    // are not read.
                    *x = if on { value(t, i, j) } else { f32::NAN };
                }
            }
            let got = ok(venv.step_flat(&flat, Some(&mask)));
            let got: Vec<Option<StepResult>> = got.into_iter().map(|s| s.map(ok)).collect();
            assert_eq!(&got, want, "{threads} threads, step {t}");
        }
    }
}

#[test]
fn thread_counts_are_capped_by_the_environment_count() {
    let make = |n: usize| -> Vec<Box<dyn Env>> {
        (0..n).map(|_| ok(ok(family("cheetah_dir")).make(0))).collect()
    };
    for (n, threads, used) in [(3, 8, 3), (3, 0, 1), (3, 1, 1), (3, 2, 2), (1, 4, 1), (0, 4, 1)] {
        let venv = VecEnv::new(make(n), threads);
        assert_eq!((venv.len(), venv.is_empty(), venv.threads()), (n, n == 0, used));
    }
    let mut empty = VecEnv::new(Vec::new(), 4);
    assert_eq!(ok(empty.reset(&[])), Vec::<Vec<f32>>::new());
    assert_eq!(ok(empty.step_flat(&[], None)).len(), 0);
    assert_eq!(ok(empty.step(&[])).len(), 0);
}

#[test]
fn dropping_joins_the_workers_whatever_was_done() {
    let make =
        || -> Vec<Box<dyn Env>> { (0..4).map(|_| ok(ok(family("cheetah_dir")).make(1))).collect() };
    // Never used, only reset, reset and stepped: each drop must return (a hang fails the test).
    drop(VecEnv::new(make(), 4));
    let mut venv = VecEnv::new(make(), 3);
    ok(venv.reset(&[1, 2, 3, 4]));
    drop(venv);
    let mut venv = VecEnv::new(make(), 2);
    ok(venv.reset(&[1, 2, 3, 4]));
    ok(venv.step_flat(&vec![0.1; venv.flat_action_len()], None));
    drop(venv);
}

#[test]
fn inputs_of_the_wrong_size_are_refused_and_the_vec_env_still_works() {
    let mut venv = VecEnv::new(mixed(), 2);
    assert!(venv.reset(&[1, 2]).is_err());
    ok(venv.reset(&[0; 5]));
    let n = venv.flat_action_len();
    assert!(venv.step_flat(&vec![0.0; n - 1], None).is_err());
    assert!(venv.step_flat(&vec![0.0; n], Some(&[true; 4])).is_err());
    assert!(venv.reset_some(&[(5, 1)]).is_err());
    assert!(venv.reset_some(&[(1, 1), (1, 2)]).is_err());
    assert_eq!(ok(venv.reset_some(&[])), Vec::<Vec<f32>>::new());
    // An action refused by one environment is that environment's error only.
    let mut flat = vec![0.0; n];
    flat[7] = f32::INFINITY; // environment 1's second value
    let out = ok(venv.step_flat(&flat, None));
    assert!(matches!(out[1], Some(Err(EnvError::NonFiniteAction { index: 1, .. }))), "{out:?}");
    assert!(out.iter().enumerate().all(|(i, s)| i == 1 || matches!(s, Some(Ok(_)))));
}

/// Panics when stepped with an action above 100.
struct Fragile(usize);

impl Env for Fragile {
    fn obs_dim(&self) -> usize {
        1
    }
    fn act_dim(&self) -> usize {
        1
    }
    fn horizon(&self) -> usize {
        10
    }
    fn reset(&mut self, _seed: u64) -> Vec<f32> {
        vec![0.0]
    }
    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError> {
        if action[0] > 100.0 {
            panic!("fragile environment {} broke", self.0);
        }
        Ok(StepResult {
            obs: vec![action[0]],
            reward: 0.0,
            terminated: false,
            truncated: false,
            success: None,
        })
    }
}

#[test]
fn a_panicking_environment_panics_the_caller_then_the_vec_env_refuses_calls() {
    // With 2 threads, environment 0 is on the calling thread, environment 1 on the worker.
    for victim in [0usize, 1] {
        let envs: Vec<Box<dyn Env>> =
            (0..4).map(|i| Box::new(Fragile(i)) as Box<dyn Env>).collect();
        let mut venv = VecEnv::new(envs, 2);
        ok(venv.reset(&[0; 4]));
        let fine = ok(venv.step_flat(&[1.0, 2.0, 3.0, 4.0], None));
        assert_eq!(
            fine[3].as_ref().map(|s| s.as_ref().map(|r| r.obs.clone())),
            Some(Ok(vec![4.0]))
        );
        let mut acts = [1.0; 4];
        acts[victim] = 1000.0;
        let caught = panic::catch_unwind(AssertUnwindSafe(|| venv.step_flat(&acts, None)));
        let Err(payload) = caught else {
            panic!("environment {victim}: no panic reached the caller")
        };
        let message = payload.downcast_ref::<String>().cloned().unwrap_or_default();
        assert_eq!(message, format!("fragile environment {victim} broke"));
        match venv.step_flat(&[1.0; 4], None) {
            Err(EnvError::Simulation { env, message }) => {
                assert_eq!(env, "VecEnv");
                assert!(message.contains("panicked"), "{message}");
            }
            other => panic!("environment {victim}: a broken VecEnv stepped: {other:?}"),
        }
        assert!(venv.reset(&[0; 4]).is_err());
        drop(venv); // must not hang
    }
}
