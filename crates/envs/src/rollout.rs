//! The batched rollout loop over a [`VecEnv`], written once: every running episode is stepped
//! together with one batched policy call per environment step, until all have ended.
//!
//! Its users (the Prompt-DT evaluation in `pdt-eval`, MACAW's evaluation episodes in `pdt-macaw`
//! and the RL collectors in `pdt-rl`) differ in how they act (a transformer over a history, an MLP
//! on the observation, an actor with per-episode noise) and in what they keep of each step; that is
//! the [`BatchPolicy`] they implement. The loop itself (which episodes run, the flat action buffer,
//! the masked step, which episodes go on) is [`run_batch`]. Creating the environments and resetting
//! them stays with the caller: the evaluation resets a window of a larger [`VecEnv`] at a time,
//! the others all of theirs.

use crate::vec_env::VecEnv;
use crate::{EnvError, StepResult};
use pdt_base::stop::StopFlag;
use std::cell::RefCell;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

/// A count of finished episodes, shared by its clones: the threads playing them add to it, a
/// front end reads it to show progress. Not a setting: it compares equal to any other count, as
/// [`StopFlag`] does, so configurations that carry one still compare by their settings.
#[derive(Debug, Clone, Default)]
pub struct EpisodeCount(Arc<AtomicUsize>);

impl EpisodeCount {
    pub fn add(&self, n: usize) {
        self.0.fetch_add(n, Ordering::Relaxed);
    }

    pub fn get(&self) -> usize {
        self.0.load(Ordering::Relaxed)
    }
}

impl PartialEq for EpisodeCount {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

/// A front end's watch over the rollouts of one long call (Python's `promptdt.evaluate`: Ctrl-C
/// and progress): [`run_batch`] checks `stop` before every step, returning
/// [`EnvError::Interrupted`] through [`BatchPolicy::batch_error`] once it is set, and adds each
/// episode that ends to `episodes`. It is set for a scope on the calling thread ([`watching`])
/// rather than passed down, because the evaluations (Prompt-DT's with its strategies and
/// adaptations, MACAW's) reach `run_batch` through learners and settings that have no place for
/// it, and `run_batch` runs on the thread that called them.
#[derive(Debug, Clone, Default)]
pub struct Watch {
    pub stop: StopFlag,
    pub episodes: EpisodeCount,
}

thread_local! {
    static WATCH: RefCell<Option<Watch>> = const { RefCell::new(None) };
}

/// Runs `f` with `watch` over every [`run_batch`] it makes on this thread (the previous watch, if
/// any, is restored afterwards, also when `f` panics).
pub fn watching<T>(watch: &Watch, f: impl FnOnce() -> T) -> T {
    struct Restore(Option<Watch>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let previous = self.0.take();
            WATCH.with(|w| *w.borrow_mut() = previous);
        }
    }
    let _restore = Restore(WATCH.with(|w| w.borrow_mut().replace(watch.clone())));
    f()
}

/// What a batched rollout asks of its caller. Slots are indices into the [`VecEnv`].
pub trait BatchPolicy {
    type Error;

    /// The actions of the running episodes `slots` (ascending), concatenated in that order, each
    /// as long as its environment's action.
    fn act(&mut self, slots: &[usize]) -> Result<Vec<f32>, Self::Error>;

    /// Whether the episode in `slot` ends here, without being stepped with `action` (e.g. a policy
    /// that gave a non-finite action). Never, by default.
    fn ends_before_step(&mut self, _slot: usize, _action: &[f32]) -> bool {
        false
    }

    /// Records the step of the episode in `slot` taken with `action`; returns whether that episode
    /// has ended.
    fn record(
        &mut self,
        slot: usize,
        action: &[f32],
        step: Result<StepResult, EnvError>,
    ) -> Result<bool, Self::Error>;

    /// The error for a failure of the whole batch `slots` (of the [`VecEnv`] itself, or actions
    /// of the wrong length), not of one environment.
    fn batch_error(&self, slots: &[usize], error: EnvError) -> Self::Error;
}

fn internal(message: String) -> EnvError {
    EnvError::Simulation { env: "rollout".into(), message }
}

/// Steps the episodes in `slots` (already reset; ascending) until each has ended, one
/// [`BatchPolicy::act`] per step for all those still running. An episode's steps depend only on its
/// own environment and actions, so the results do not depend on which episodes share the batch
/// beyond what the policy's batched computation does.
pub fn run_batch<P: BatchPolicy>(
    venv: &mut VecEnv,
    slots: Vec<usize>,
    policy: &mut P,
) -> Result<(), P::Error> {
    let mut flat = vec![0f32; venv.flat_action_len()];
    let mut mask = vec![false; venv.len()];
    let mut active = slots;
    let watch = WATCH.with(|w| w.borrow().clone());
    while !active.is_empty() {
        if watch.as_ref().is_some_and(|w| w.stop.is_set()) {
            return Err(policy.batch_error(&active, EnvError::Interrupted));
        }
        let mut ended = 0;
        let actions = policy.act(&active)?;
        // (slot, its action's range in `actions`) for the episodes stepped this time.
        let mut stepped = Vec::with_capacity(active.len());
        let mut offset = 0;
        for &slot in &active {
            let Some(range) = venv.action_range(slot) else {
                let error = internal(format!("no environment in slot {slot}"));
                return Err(policy.batch_error(&active, error));
            };
            let width = range.len();
            let own = offset..offset + width;
            offset += width;
            let Some(action) = actions.get(own.clone()) else {
                let error = EnvError::ActionDim {
                    env: "rollout".into(),
                    got: actions.len(),
                    expected: offset,
                };
                return Err(policy.batch_error(&active, error));
            };
            if policy.ends_before_step(slot, action) {
                ended += 1;
                continue;
            }
            flat[range].copy_from_slice(action);
            mask[slot] = true;
            stepped.push((slot, own));
        }
        if stepped.is_empty() {
            count_ended(&watch, ended);
            break;
        }
        let steps = venv.step_flat(&flat, Some(&mask));
        for (slot, _) in &stepped {
            mask[*slot] = false;
        }
        let mut steps = steps.map_err(|e| policy.batch_error(&active, e))?;
        let mut still = Vec::with_capacity(stepped.len());
        for (slot, own) in stepped {
            let step = steps.get_mut(slot).and_then(Option::take).unwrap_or_else(|| {
                Err(internal(format!("the episode in slot {slot} was not stepped")))
            });
            if policy.record(slot, &actions[own], step)? {
                ended += 1;
            } else {
                still.push(slot);
            }
        }
        count_ended(&watch, ended);
        active = still;
    }
    Ok(())
}

fn count_ended(watch: &Option<Watch>, ended: usize) {
    if let Some(w) = watch {
        w.episodes.add(ended);
    }
}
