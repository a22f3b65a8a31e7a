//! The evaluation's environment pool: episodes of different lengths leaving batches of any size,
//! on any number of environment threads, take the sequential loop's actions; an environment's
//! error names its task.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_envs::{Env, EnvError, StepResult};
use pdt_eval::{evaluate, EvalError, EvalReturns, EvalSettings, EvalTask};
use pdt_model::{PromptDt, PromptDtConfig};
use pdt_prompt::StateNorm;
use pdt_rundir::config::Inference;
use tch::{nn::VarStore, Device};

/// A point robot whose episode ends (terminates) after `3 + seed % 7` steps, or that refuses its
/// third action when `refuse` is set.
struct Ending {
    inner: Box<dyn Env>,
    end_at: usize,
    t: usize,
    refuse: bool,
}

impl Env for Ending {
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.inner.act_dim()
    }
    fn horizon(&self) -> usize {
        self.inner.horizon()
    }
    fn reset(&mut self, seed: u64) -> Vec<f32> {
        self.end_at = 3 + (seed % 7) as usize;
        self.t = 0;
        self.inner.reset(seed)
    }
    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError> {
        self.t += 1;
        if self.refuse && self.t == 3 {
            return Err(EnvError::Simulation { env: "ending".into(), message: "refused".into() });
        }
        let mut r = self.inner.step(action)?;
        r.terminated |= self.t >= self.end_at;
        Ok(r)
    }
}

fn tasks(refuse_in: Option<usize>) -> Vec<EvalTask> {
    let family = pdt_envs::family("point_robot").unwrap();
    [3usize, 11, 25]
        .iter()
        .enumerate()
        .map(|(k, &i)| EvalTask {
            name: format!("point_robot-{i}"),
            index: i,
            envs: (0..5)
                .map(|_| {
                    Box::new(Ending {
                        inner: family.make(i).unwrap(),
                        end_at: 0,
                        t: 0,
                        refuse: refuse_in == Some(k),
                    }) as Box<dyn Env>
                })
                .collect(),
            seeds: (0..5).map(|e| (k * 5 + e) as u64).collect(),
            prompt: None,
            target_return: None,
        })
        .collect()
}

fn settings(max_batch: usize, env_threads: usize) -> EvalSettings {
    EvalSettings {
        k: 10,
        horizon: 20,
        rtg_scale: 10.0,
        target_return: 0.0,
        returns: EvalReturns::Constant,
        norm: StateNorm { mean: vec![0.1, 0.3], std: vec![0.5, 0.4] },
        max_batch,
        device: Device::Cpu,
        env_threads,
        inference: Inference::Full,
    }
}

fn model() -> (VarStore, PromptDt) {
    // One libtorch thread: batched and single forwards then agree bitwise (see
    // batched_vs_sequential.rs).
    let _torch = pdt_testkit::process::libtorch(); // seeds the process's generator
    tch::set_num_threads(1);
    tch::manual_seed(3);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &PromptDtConfig::reference(2, 2));
    (vs, model)
}

#[test]
fn episodes_leaving_batches_take_the_sequential_actions_on_any_thread_count() {
    let (_vs, model) = model();
    let sequential = evaluate(&model, tasks(None), &settings(1, 1)).unwrap();
    let lengths: Vec<usize> = sequential.iter().map(|e| e.length).collect();
    assert_eq!(lengths, (0..15).map(|s| 3 + s % 7).collect::<Vec<_>>());
    for (max_batch, env_threads) in [(1, 4), (2, 2), (4, 3), (6, 2), (4096, 3), (4096, 20)] {
        let batched = evaluate(&model, tasks(None), &settings(max_batch, env_threads)).unwrap();
        assert_eq!(batched.len(), 15);
        for (b, s) in batched.iter().zip(&sequential) {
            assert_eq!((b.task_index, b.seed, b.length), (s.task_index, s.seed, s.length));
            let same = b.actions.iter().zip(&s.actions).all(|(x, y)| x.to_bits() == y.to_bits());
            let diff =
                b.actions.iter().zip(&s.actions).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
            let what = format!("max_batch {max_batch}, {env_threads} threads, seed {}", b.seed);
            // Bit for bit on batch-invariant kernels (AVX2), within BATCH_TOLERANCE on AVX-512.
            if pdt_testkit::cpu::batch_invariant() {
                assert!(same, "{what}: actions differ by up to {diff:e}");
                assert_eq!(b.episode_return.to_bits(), s.episode_return.to_bits());
            } else {
                assert!(diff <= pdt_testkit::cpu::BATCH_TOLERANCE, "{what}: {diff:e}");
                assert!((b.episode_return - s.episode_return).abs() <= 1e-4, "{what}");
            }
        }
    }
}

#[test]
fn an_environment_error_names_its_task() {
    let (_vs, model) = model();
    for (max_batch, env_threads) in [(1, 1), (4096, 2)] {
        match evaluate(&model, tasks(Some(1)), &settings(max_batch, env_threads)) {
            Err(EvalError::Env { task, source }) => {
                assert_eq!(task, "point_robot-11");
                assert!(source.to_string().contains("refused"), "{source}");
            }
            other => panic!("{:?}", other.map(|eps| eps.len())),
        }
    }
}
