//! An episode acted on by a [`Policy`]: its history (normalised states, actions, returns-to-go),
//! the action given last, and the checks of what comes in (observation, reward, target return,
//! the model's `max_ep_len`, return-to-go overflow). A step whose action comes out not finite is
//! taken back, so one bad input never stays in later contexts. `promptdt serve` and the Python
//! `Policy` keep their episodes as these.

use crate::inputs::{finite_f32, Inputs, MAX_RETURN};
use crate::{Policy, PolicyError};
use pdt_eval::{first_rtg, EvalReturns, History};

/// An observation checked for a policy: `obs_dim` finite f32 values whose normalisation is finite
/// too (a finite 3e38 normalises to infinity, and one infinite state makes every action of its
/// context NaN).
#[derive(Debug, Clone)]
pub struct Observation {
    values: Vec<f32>,
    inputs: Inputs,
}

impl Observation {
    /// Where the values of what comes with this observation (a prompt) are recorded.
    pub fn inputs_mut(&mut self) -> &mut Inputs {
        &mut self.inputs
    }
}

/// The first return token of an episode: the run's target return or one given, checked.
#[derive(Debug, Clone, Copy)]
pub struct Target {
    rtg: f32,
    /// The target return given (`None`: the run's).
    given: Option<f32>,
}

/// A reward and the observation after it, checked for a policy, to record in an episode.
#[derive(Debug, Clone)]
pub struct Step {
    reward: f64,
    obs: Observation,
}

/// What [`History::record`] changed, to take a refused step back.
#[derive(Debug, Clone)]
struct Undo {
    states: usize,
    actions: usize,
    rtg: usize,
    ret: f64,
    t: usize,
    last_action: Vec<f32>,
}

/// One episode's state.
#[derive(Debug, Clone)]
pub struct Episode {
    history: History,
    /// The action accepted last (recorded with the next reward and observation); empty before the
    /// first.
    last_action: Vec<f32>,
    /// How to take back the step whose action is being computed, should that action not be
    /// finite.
    undo: Option<Undo>,
    /// The largest inputs of the action being computed, named, for the error if it is not finite.
    inputs: Inputs,
}

impl Policy {
    /// A raw observation checked (see [`Observation`]).
    pub fn observation(&self, obs: &[f64]) -> Result<Observation, PolicyError> {
        let ds = self.stats.obs_dim;
        if obs.len() != ds {
            return Err(PolicyError::Input(format!(
                "observation has {} values, the policy takes {ds}",
                obs.len()
            )));
        }
        let values = finite_f32("observation", obs)?;
        let mut inputs = Inputs::default();
        for (j, &x) in values.iter().enumerate() {
            let (mean, std) = (self.norm.mean[j], self.norm.std[j]);
            // In f32, exactly as `History` normalises it.
            let z = (x - mean) / std;
            if !z.is_finite() {
                return Err(PolicyError::Input(format!(
                    "observation[{j}] = {x:e} is out of range: normalised with the run's state \
                     statistics ((x - mean) / std, mean {mean}, std {std}) it is beyond the \
                     largest f32 ({:e})",
                    f32::MAX
                )));
            }
            inputs.see(|| format!("observation[{j}] = {x:e}"), z);
        }
        Ok(Observation { values, inputs })
    }

    /// The first return token of an episode aiming at `target_return` (`None`: the run's G*),
    /// which must be finite and within [`MAX_RETURN`].
    pub fn target(&self, target_return: Option<f64>) -> Result<Target, PolicyError> {
        let given = match target_return {
            Some(g) if !g.is_finite() => {
                return Err(PolicyError::Input(format!("target_return {g} is not a finite number")))
            }
            Some(g) if g.abs() > MAX_RETURN => {
                return Err(PolicyError::Input(format!(
                    "target_return {g:e} is outside the accepted range [-{MAX_RETURN:e}, \
                     {MAX_RETURN:e}] (returns are f32 tokens)"
                )))
            }
            Some(g) => Some(g as f32),
            None => None,
        };
        let target = given.unwrap_or(self.stats.target_return);
        Ok(Target { rtg: first_rtg(self.returns, target, self.stats.rtg_scale), given })
    }

    /// An episode at its first observation.
    pub fn start(&self, obs: Observation, target: Target) -> Episode {
        let mut inputs = obs.inputs;
        if let Some(g) = target.given {
            inputs.see(|| format!("target_return = {g:e}"), target.rtg);
        }
        Episode {
            history: History::start(&self.norm, &obs.values, target.rtg),
            last_action: Vec::new(),
            undo: None,
            inputs,
        }
    }

    /// A reward (finite, within [`MAX_RETURN`]) and the observation after it.
    pub fn step(&self, reward: f64, obs: Observation) -> Result<Step, PolicyError> {
        let r = reward;
        if !r.is_finite() {
            return Err(PolicyError::Input(format!("reward {r} is not a finite number")));
        }
        if r.abs() > MAX_RETURN {
            return Err(PolicyError::Input(format!(
                "reward {r:e} is outside the accepted range [-{MAX_RETURN:e}, {MAX_RETURN:e}] \
                 (returns are f32 tokens)"
            )));
        }
        Ok(Step { reward, obs })
    }

    /// The return-to-go token `step`'s reward leads to in `e`, computed as [`History::record`]
    /// will: rewards within range can still add up beyond it, and the token stays in every later
    /// context.
    fn next_rtg(&self, e: &Episode, step: &Step) -> Result<f32, PolicyError> {
        let max_ep_len = self.max_ep_len();
        if e.history.t + 1 >= max_ep_len {
            return Err(PolicyError::EpisodeFull { max_ep_len });
        }
        let (r, scale) = (step.reward, self.stats.rtg_scale);
        let prev = e.history.rtg.last().copied().unwrap_or(0.0);
        let next = match self.returns {
            EvalReturns::Decreasing => prev - r as f32 / scale,
            EvalReturns::Constant | EvalReturns::Zero => prev,
        };
        let rtg = f64::from(next) * f64::from(scale);
        if !next.is_finite() || rtg.abs() > MAX_RETURN {
            return Err(PolicyError::Input(format!(
                "reward {r:e} would take the episode's return-to-go (the target return minus \
                 the rewards so far) to {rtg:e}, outside the accepted range [-{MAX_RETURN:e}, \
                 {MAX_RETURN:e}]; the step is refused and the episode is as it was"
            )));
        }
        Ok(next)
    }

    /// Whether `step` can be recorded in `e`: the episode is short of the model's `max_ep_len`,
    /// and its return-to-go stays within [`MAX_RETURN`]. Changes nothing.
    pub fn check(&self, e: &Episode, step: &Step) -> Result<(), PolicyError> {
        self.next_rtg(e, step).map(|_| ())
    }

    /// Records the last action's reward and the observation after it in `e` (after
    /// [`Policy::check`]), keeping what it takes to take the step back.
    pub fn record(&self, e: &mut Episode, step: Step) -> Result<(), PolicyError> {
        let next = self.next_rtg(e, &step)?;
        let Step { reward: r, obs } = step;
        let mut inputs = obs.inputs;
        let rtg = f64::from(next) * f64::from(self.stats.rtg_scale);
        inputs.see(|| format!("the return-to-go {rtg:e} after reward = {r:e}"), next);
        e.undo = Some(Undo {
            states: e.history.states.len(),
            actions: e.history.actions.len(),
            rtg: e.history.rtg.len(),
            ret: e.history.ret,
            t: e.history.t,
            last_action: e.last_action.clone(),
        });
        e.inputs = inputs;
        let last = std::mem::take(&mut e.last_action);
        let (returns, scale) = (self.returns, self.stats.rtg_scale);
        e.history.record(&last, r as f32, &obs.values, &self.norm, returns, scale);
        Ok(())
    }

    /// The next action of each episode, `[A * act_dim]`, in one forward (with `prefix`, one row
    /// per episode, or none for the methods without a prompt). Each episode then
    /// [`Episode::accept`]s its row.
    pub fn act(&self, episodes: &[&Episode], prefix: Option<&pdt_model::PrefixCache>) -> Vec<f32> {
        self.act_with(episodes, prefix, None)
    }

    /// [`Policy::act`] through a task's LoRA adapters (`prefix` made with the same adapters:
    /// `pdt_eval::testtime::TaskAdaptation::prefix`).
    pub fn act_with(
        &self,
        episodes: &[&Episode],
        prefix: Option<&pdt_model::PrefixCache>,
        lora: Option<&pdt_model::LoraAdapters>,
    ) -> Vec<f32> {
        let hs: Vec<&History> = episodes.iter().map(|e| &e.history).collect();
        self.forward_with(&hs, prefix, lora)
    }
}

impl Episode {
    /// Steps taken.
    pub fn t(&self) -> usize {
        self.history.t
    }

    /// Undiscounted return so far.
    pub fn ret(&self) -> f64 {
        self.history.ret
    }

    pub fn history(&self) -> &History {
        &self.history
    }

    /// The action computed for the episode's last observation: kept when finite (it is recorded
    /// with the next reward); otherwise the step is taken back ([`Episode::take_back`]) and the
    /// error names the largest input. Inputs each representable can still overflow inside the
    /// model (an embedding of 1e30 squared in a layer norm).
    pub fn accept(&mut self, action: &[f32]) -> Result<(), PolicyError> {
        if action.iter().all(|x| x.is_finite()) {
            self.undo = None;
            self.last_action = action.to_vec();
            return Ok(());
        }
        let inputs = self.inputs.describe();
        self.take_back();
        Err(PolicyError::ActionNotFinite { action: action.to_vec(), inputs })
    }

    /// Takes back the step recorded last, whose action was not accepted: the episode is as it was
    /// before it. (An episode at its first observation has nothing to take back; its owner drops
    /// it.)
    pub fn take_back(&mut self) {
        if let Some(u) = self.undo.take() {
            self.history.states.truncate(u.states);
            self.history.actions.truncate(u.actions);
            self.history.rtg.truncate(u.rtg);
            self.history.ret = u.ret;
            self.history.t = u.t;
            self.last_action = u.last_action;
        }
    }
}
