//! [`WorkerEnvs`]: a [`Backend`] whose environments a Python worker makes and steps, one request
//! per vector reset or step. What the worker answers is checked here (sizes, finite
//! observations), each error naming the task and the step; the episode's time limit is counted
//! here too, so an environment that never ends its episodes is cut at the family's horizon.

use std::time::Duration;

use super::protocol::{parse_reply, Reply, VERSION};
use super::spec::WorkerTask;
use super::Transport;
use crate::vec_env::{Backend, EnvDims, StepSlot};
use crate::{EnvError, StepResult};

/// A policy's action for one environment's new observation, where one was asked for
/// (`super::Acting`): the action, or why there is none (the policy raised, or returned an action
/// of another size or with a non-finite value), naming the task and the step it was for.
pub type Acted = Option<Result<Vec<f32>, EnvError>>;

/// The first observation of each environment reset (`None` where it was not).
pub type Resets = Vec<Option<Vec<f32>>>;

/// Time a worker gets to start: import its packages (promptdt's libtorch, the environment's) and
/// make every environment, which can take much longer than a step.
const START_TIMEOUT: Duration = Duration::from_secs(300);

/// Environments in a Python worker (see the module docs).
pub(super) struct WorkerEnvs {
    transport: Box<dyn Transport>,
    /// The task of each environment.
    tasks: Vec<WorkerTask>,
    dims: EnvDims,
    step_timeout: Duration,
    /// Steps taken in each environment's episode; `None` before its first reset and once the
    /// episode ended.
    steps: Vec<Option<usize>>,
    /// Set once a call failed as a whole: the worker is gone.
    broken: Option<String>,
}

impl WorkerEnvs {
    /// Makes an environment of each task, all of sizes `dims`, on the Python side of `transport`:
    /// by `spec` (a suite's `[environment]`, as JSON), or, where it is `null`, by the factory that
    /// side was given. Each later request may take `step_timeout`.
    /// `policies`: a collection's policies by name (`{"expert": "module:callable" or null}`,
    /// `null` where that side was given the callable); `Null` for an evaluation.
    pub(super) fn start(
        transport: Box<dyn Transport>,
        spec: serde_json::Value,
        step_timeout: Duration,
        tasks: Vec<WorkerTask>,
        dims: EnvDims,
        policies: serde_json::Value,
    ) -> Result<Self, EnvError> {
        let n = tasks.len();
        let mut me =
            Self { transport, tasks, dims, step_timeout, steps: vec![None; n], broken: None };
        let mut header = serde_json::json!({
            "op": "init",
            "protocol": VERSION,
            "spec": spec,
            "tasks": me.tasks,
            "obs_dim": dims.obs_dim,
            "act_dim": dims.act_dim,
        });
        if !policies.is_null() {
            header["policies"] = policies;
        }
        let all: Vec<usize> = (0..n).collect();
        let (reply, _) = me.call(&header, &[], START_TIMEOUT, &all, None)?;
        if !reply.ok {
            return Err(me.malformed(&all, None, "`init` answered without `ok`".into()));
        }
        Ok(me)
    }

    /// `name (task i)` of environment `slot`.
    fn task(&self, slot: usize) -> String {
        self.tasks.get(slot).map_or_else(|| format!("environment {slot}"), task_label)
    }

    /// One request; a failure of the whole call (the worker died, hung, answered nonsense or
    /// reported an error) marks the worker broken and names the tasks of `slots` (or the one the
    /// worker named) and `step`.
    fn call(
        &mut self,
        header: &serde_json::Value,
        payload: &[f32],
        timeout: Duration,
        slots: &[usize],
        step: Option<usize>,
    ) -> Result<(Reply, Vec<f32>), EnvError> {
        if let Some(why) = &self.broken {
            return Err(EnvError::Worker {
                task: tasks_label(&self.tasks, slots.iter().copied()),
                step,
                message: format!("the worker is gone since an earlier failure: {why}"),
            });
        }
        let answer = self.transport.call(&header.to_string(), payload, timeout);
        let (task, message) = match answer.map(|(h, v)| (parse_reply(&h), v)) {
            Ok((Ok(reply), values)) => match reply.error.clone() {
                None => return Ok((reply, values)),
                Some(e) => (reply.slot.map(|s| self.task(s)), e),
            },
            Ok((Err(why), _)) => (None, format!("the worker sent a malformed reply: {why}")),
            Err(message) => (None, message),
        };
        // Not to be asked again: a worker process is killed now, not when the VecEnv goes.
        self.transport.abandon();
        self.broken = Some(message.lines().next().unwrap_or_default().to_owned());
        let task = task.unwrap_or_else(|| tasks_label(&self.tasks, slots.iter().copied()));
        Err(EnvError::Worker { task, step, message })
    }

    /// A malformed answer: the worker is no longer trusted.
    fn malformed(&mut self, slots: &[usize], step: Option<usize>, why: String) -> EnvError {
        let message = format!("the worker sent a malformed reply: {why}");
        self.broken = Some(message.clone());
        self.transport.abandon();
        EnvError::Worker { task: tasks_label(&self.tasks, slots.iter().copied()), step, message }
    }

    /// The observation of `slot` (row `row` of `values`), checked finite.
    fn observation(&self, slot: usize, row: &[f32], step: usize) -> Result<Vec<f32>, EnvError> {
        match row.iter().position(|v| !v.is_finite()) {
            None => Ok(row.to_vec()),
            Some(i) => Err(EnvError::Worker {
                task: self.task(slot),
                step: Some(step),
                message: format!(
                    "the environment returned a non-finite observation (obs[{i}] = {})",
                    row[i]
                ),
            }),
        }
    }
}

/// `name (task i)`.
fn task_label(t: &WorkerTask) -> String {
    format!("{} (task {})", t.name, t.index)
}

/// The distinct tasks of `slots`, at most a few named.
fn tasks_label(tasks: &[WorkerTask], slots: impl Iterator<Item = usize>) -> String {
    let mut names: Vec<String> = Vec::new();
    for t in slots.filter_map(|s| tasks.get(s)).map(task_label) {
        if !names.contains(&t) {
            names.push(t);
        }
    }
    match names.len() {
        0 => "the worker".to_owned(),
        1..=4 => names.join(", "),
        n => format!("{} and {} other tasks", names[..3].join(", "), n - 3),
    }
}

impl WorkerEnvs {
    /// Resets the environments whose seed is given; with `act` (one policy name or `None` per
    /// environment), also the named policy's action on each first observation.
    pub(super) fn reset_acting(
        &mut self,
        seeds: &[Option<u64>],
        act: Option<&[Option<String>]>,
    ) -> Result<(Resets, Vec<Acted>), EnvError> {
        let slots: Vec<usize> = (0..seeds.len()).filter(|&i| seeds[i].is_some()).collect();
        let mut out: Vec<Option<Vec<f32>>> = vec![None; seeds.len()];
        let mut acted: Vec<Acted> = (0..seeds.len()).map(|_| None).collect();
        if slots.is_empty() {
            return Ok((out, acted));
        }
        let mut header = serde_json::json!({"op": "reset", "seeds": seeds});
        if let Some(act) = act {
            header["act"] = serde_json::json!(act);
        }
        let (reply, values) = self.call(&header, &[], self.step_timeout, &slots, Some(0))?;
        let (od, ad) = (self.dims.obs_dim, self.dims.act_dim);
        let asked =
            asked_slots(&slots, |_, i| act.is_some_and(|a| a.get(i).is_some_and(|n| n.is_some())));
        if reply.slots != slots || values.len() != slots.len() * od + reply.acted.len() * ad {
            let why = format!(
                "reset of environments {slots:?} answered environments {:?} with {} values \
                 ({od} per observation, then {ad} per action of {:?})",
                reply.slots,
                values.len(),
                reply.acted
            );
            return Err(self.malformed(&slots, Some(0), why));
        }
        let (obs, actions) = values.split_at(slots.len() * od);
        for (&slot, row) in slots.iter().zip(obs.chunks_exact(od.max(1))) {
            out[slot] = Some(self.observation(slot, &row[..od], 0)?);
            self.steps[slot] = Some(0);
        }
        let going = vec![true; seeds.len()];
        self.policy_actions(&reply, actions, &asked, &going, &mut acted, |_| 1)?;
        Ok((out, acted))
    }

    /// Steps the environments of `mask` with their rows of `actions`; with `act` (one policy
    /// name or `None` per environment), also the named policy's action on each new observation
    /// of an episode that goes on.
    pub(super) fn step_acting(
        &mut self,
        actions: &[f32],
        mask: &[bool],
        act: Option<&[Option<String>]>,
    ) -> Result<(Vec<StepSlot>, Vec<Acted>), EnvError> {
        let (od, ad) = (self.dims.obs_dim, self.dims.act_dim);
        let mut out: Vec<StepSlot> = (0..mask.len()).map(|_| None).collect();
        let mut acted: Vec<Acted> = (0..mask.len()).map(|_| None).collect();
        let mut slots = Vec::new();
        let mut sent = Vec::new();
        for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
            if self.steps.get(i).copied().flatten().is_none() {
                out[i] = Some(Err(EnvError::Finished { env: self.task(i) }));
                continue;
            }
            let Some(a) = actions.get(i * ad..(i + 1) * ad) else {
                return Err(self.malformed(
                    &[i],
                    None,
                    "actions too short (internal error)".into(),
                ));
            };
            slots.push(i);
            sent.extend_from_slice(a);
        }
        if slots.is_empty() {
            return Ok((out, acted));
        }
        // The step being taken, of the first environment stepped (those of one batch of episodes
        // started together).
        let step = self.steps[slots[0]].map(|t| t + 1);
        let mut header = serde_json::json!({"op": "step", "slots": slots, "payload": sent.len()});
        // A policy is not asked for an episode that the horizon cuts at this step.
        let names: Option<Vec<Option<String>>> = act.map(|act| {
            slots
                .iter()
                .map(|&i| {
                    let t = self.steps[i].unwrap_or(0) + 1;
                    act.get(i).cloned().flatten().filter(|_| t < self.dims.horizon)
                })
                .collect()
        });
        if let Some(names) = &names {
            header["act"] = serde_json::json!(names);
        }
        let (reply, values) = self.call(&header, &sent, self.step_timeout, &slots, step)?;
        let n = slots.len();
        let sizes = [reply.terminated.len(), reply.truncated.len(), reply.success.len()];
        let want = n * (od + 1) + reply.acted.len() * ad;
        if reply.slots != slots || values.len() != want || sizes != [n; 3] {
            let why = format!(
                "step of environments {slots:?} answered environments {:?} with {} values \
                 ({od} per observation, then a reward each, then {ad} per action of {:?}) and \
                 {sizes:?} flags",
                reply.slots,
                values.len(),
                reply.acted
            );
            return Err(self.malformed(&slots, step, why));
        }
        let (obs, rest) = values.split_at(n * od);
        let (rewards, actions) = rest.split_at(n);
        let before: Vec<usize> = slots.iter().map(|&i| self.steps[i].unwrap_or(0)).collect();
        for (k, &slot) in slots.iter().enumerate() {
            let t = before[k] + 1;
            if let Some((_, e)) = reply.errors.iter().find(|(s, _)| *s == slot) {
                // The environment raised: its episode cannot go on.
                self.steps[slot] = None;
                let message = format!("the environment's step raised: {e}");
                out[slot] =
                    Some(Err(EnvError::Worker { task: self.task(slot), step: Some(t), message }));
                continue;
            }
            let result = self.observation(slot, &obs[k * od..(k + 1) * od], t).map(|obs| {
                let truncated = reply.truncated[k] || t >= self.dims.horizon;
                StepResult {
                    obs,
                    reward: rewards[k],
                    terminated: reply.terminated[k],
                    truncated,
                    success: reply.success[k],
                }
            });
            let ended = result.as_ref().map_or(true, |r| r.terminated || r.truncated);
            self.steps[slot] = (!ended).then_some(t);
            out[slot] = Some(result);
        }
        if let Some(names) = &names {
            // Asked: the slots named. The worker acts for those whose episode goes on in its
            // view; one this side ended (a non-finite observation) gets no action.
            let asked = asked_slots(&slots, |k, _| names[k].is_some());
            let going: Vec<bool> = (0..mask.len()).map(|i| self.steps[i].is_some()).collect();
            let at =
                |slot: usize| slots.iter().position(|&s| s == slot).map_or(1, |k| before[k] + 2);
            self.policy_actions(&reply, actions, &asked, &going, &mut acted, at)?;
        }
        Ok((out, acted))
    }

    /// The policies' actions of a reply into `acted` (by environment): the rows of `values`,
    /// one per `reply.acted`, checked finite, and `reply.policy_errors`, for the environments
    /// `going` on. Each answer must be for a slot of `asked`, and every slot of `asked` still
    /// going must have one. `step(slot)`: the step the action is for, for messages.
    fn policy_actions(
        &mut self,
        reply: &Reply,
        values: &[f32],
        asked: &[usize],
        going: &[bool],
        acted: &mut [Acted],
        step: impl Fn(usize) -> usize,
    ) -> Result<(), EnvError> {
        let ad = self.dims.act_dim;
        let answered: Vec<usize> =
            reply.acted.iter().chain(reply.policy_errors.iter().map(|(s, _)| s)).copied().collect();
        let stray = answered.iter().any(|s| !asked.contains(s));
        let missing = asked.iter().any(|s| going.get(*s) == Some(&true) && !answered.contains(s));
        if stray || missing {
            let why = format!(
                "policy actions were asked for environments {asked:?}; it answered {:?} and \
                 errors for {:?}",
                reply.acted,
                reply.policy_errors.iter().map(|(s, _)| s).collect::<Vec<_>>()
            );
            return Err(self.malformed(asked, None, why));
        }
        let going = |slot: &usize| going.get(*slot) == Some(&true);
        for (&slot, row) in reply.acted.iter().zip(values.chunks_exact(ad.max(1))) {
            if !going(&slot) {
                continue;
            }
            let t = step(slot);
            acted[slot] = Some(match row.iter().position(|v| !v.is_finite()) {
                None => Ok(row.to_vec()),
                Some(i) => Err(EnvError::Worker {
                    task: self.task(slot),
                    step: Some(t),
                    message: format!(
                        "the policy returned a non-finite action (action[{i}] = {}) for the \
                         observation before this step",
                        row[i]
                    ),
                }),
            });
        }
        for (slot, e) in reply.policy_errors.iter().filter(|(s, _)| going(s)) {
            let message = format!("{e} (on the observation before this step)");
            let err = EnvError::Worker { task: self.task(*slot), step: Some(step(*slot)), message };
            acted[*slot] = Some(Err(err));
        }
        Ok(())
    }
}

/// The environments of `slots` for which `named(k, slot)` (`k`: the place in `slots`) names a
/// policy, sorted (how the worker's `acted` and `policy_errors` are compared).
fn asked_slots(slots: &[usize], named: impl Fn(usize, usize) -> bool) -> Vec<usize> {
    let mut asked: Vec<usize> =
        slots.iter().enumerate().filter(|&(k, &slot)| named(k, slot)).map(|(_, &s)| s).collect();
    asked.sort_unstable();
    asked
}

impl Backend for WorkerEnvs {
    fn reset(&mut self, seeds: &[Option<u64>]) -> Result<Vec<Option<Vec<f32>>>, EnvError> {
        Ok(self.reset_acting(seeds, None)?.0)
    }

    fn step(&mut self, actions: &[f32], mask: &[bool]) -> Result<Vec<StepSlot>, EnvError> {
        Ok(self.step_acting(actions, mask, None)?.0)
    }
}
