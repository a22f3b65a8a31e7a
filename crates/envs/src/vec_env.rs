//! [`VecEnv`]: N environments stepped together, spread over worker threads.
//!
//! Each environment owns its simulator state and draws its reset noise from its own RNG, seeded by
//! the seed given for it; environments share nothing mutable. So the results depend only on the
//! environments, seeds and actions, never on the number of threads or on scheduling.

use crate::{Env, EnvError, StepResult};

/// A batch of environments (possibly of different tasks) stepped in parallel.
pub struct VecEnv {
    envs: Vec<Box<dyn Env>>,
    threads: usize,
}

impl VecEnv {
    /// `threads` worker threads at most (0 or 1: everything on the calling thread).
    pub fn new(envs: Vec<Box<dyn Env>>, threads: usize) -> Self {
        Self { envs, threads: threads.max(1) }
    }

    pub fn len(&self) -> usize {
        self.envs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    pub fn threads(&self) -> usize {
        self.threads
    }

    /// The environments, for per-environment queries (`obs_dim`, `horizon`, ...).
    pub fn envs(&self) -> &[Box<dyn Env>] {
        &self.envs
    }

    /// Resets environment `i` with `seeds[i]`; returns the first observations, in order.
    pub fn reset(&mut self, seeds: &[u64]) -> Result<Vec<Vec<f32>>, EnvError> {
        self.check_len("seeds", seeds.len())?;
        Ok(self.map(seeds, |env, &seed| env.reset(seed)))
    }

    /// Steps environment `i` with `actions[i]`. Each environment's outcome is its own: an
    /// environment that refuses its action (wrong size, not finite, episode over) is left as it
    /// was and reports the error in its slot, while the others step.
    pub fn step(
        &mut self,
        actions: &[Vec<f32>],
    ) -> Result<Vec<Result<StepResult, EnvError>>, EnvError> {
        self.check_len("actions", actions.len())?;
        Ok(self.map(actions, |env, action| env.step(action)))
    }

    fn check_len(&self, what: &str, got: usize) -> Result<(), EnvError> {
        if got == self.envs.len() {
            Ok(())
        } else {
            Err(EnvError::Simulation {
                env: "VecEnv".into(),
                message: format!("{got} {what} for {} environments", self.envs.len()),
            })
        }
    }

    /// Applies `f` to each (environment, input) pair, in contiguous chunks on up to `threads`
    /// scoped threads, and returns the outputs in environment order.
    fn map<I: Sync, O: Send>(
        &mut self,
        inputs: &[I],
        f: impl Fn(&mut dyn Env, &I) -> O + Sync,
    ) -> Vec<O> {
        let n = self.envs.len();
        let threads = self.threads.min(n.max(1));
        if threads <= 1 {
            return self.envs.iter_mut().zip(inputs).map(|(env, x)| f(env.as_mut(), x)).collect();
        }
        let chunk = n.div_ceil(threads);
        let f = &f;
        std::thread::scope(|scope| {
            let handles: Vec<_> = self
                .envs
                .chunks_mut(chunk)
                .zip(inputs.chunks(chunk))
                .map(|(envs, xs)| {
                    scope.spawn(move || {
                        envs.iter_mut()
                            .zip(xs)
                            .map(|(env, x)| f(env.as_mut(), x))
                            .collect::<Vec<O>>()
                    })
                })
                .collect();
            let mut out = Vec::with_capacity(n);
            for h in handles {
                match h.join() {
                    Ok(part) => out.extend(part),
                    // A worker only panics if an environment panicked; pass it on unchanged.
                    Err(payload) => std::panic::resume_unwind(payload),
                }
            }
            out
        })
    }
}
