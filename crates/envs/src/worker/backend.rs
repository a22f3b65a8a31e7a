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
    pub(super) fn start(
        transport: Box<dyn Transport>,
        spec: serde_json::Value,
        step_timeout: Duration,
        tasks: Vec<WorkerTask>,
        dims: EnvDims,
    ) -> Result<Self, EnvError> {
        let n = tasks.len();
        let mut me =
            Self { transport, tasks, dims, step_timeout, steps: vec![None; n], broken: None };
        let header = serde_json::json!({
            "op": "init",
            "protocol": VERSION,
            "spec": spec,
            "tasks": me.tasks,
            "obs_dim": dims.obs_dim,
            "act_dim": dims.act_dim,
        });
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

impl Backend for WorkerEnvs {
    fn reset(&mut self, seeds: &[Option<u64>]) -> Result<Vec<Option<Vec<f32>>>, EnvError> {
        let slots: Vec<usize> = (0..seeds.len()).filter(|&i| seeds[i].is_some()).collect();
        let mut out: Vec<Option<Vec<f32>>> = vec![None; seeds.len()];
        if slots.is_empty() {
            return Ok(out);
        }
        let header = serde_json::json!({"op": "reset", "seeds": seeds});
        let (reply, values) = self.call(&header, &[], self.step_timeout, &slots, Some(0))?;
        let od = self.dims.obs_dim;
        if reply.slots != slots || values.len() != slots.len() * od {
            let why = format!(
                "reset of environments {slots:?} answered environments {:?} with {} values \
                 ({od} per observation)",
                reply.slots,
                values.len()
            );
            return Err(self.malformed(&slots, Some(0), why));
        }
        for (&slot, row) in slots.iter().zip(values.chunks_exact(od.max(1))) {
            out[slot] = Some(self.observation(slot, &row[..od], 0)?);
            self.steps[slot] = Some(0);
        }
        Ok(out)
    }

    fn step(&mut self, actions: &[f32], mask: &[bool]) -> Result<Vec<StepSlot>, EnvError> {
        let (od, ad) = (self.dims.obs_dim, self.dims.act_dim);
        let mut out: Vec<StepSlot> = (0..mask.len()).map(|_| None).collect();
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
            return Ok(out);
        }
        // The step being taken, of the first environment stepped (those of one batch of episodes
        // started together).
        let step = self.steps[slots[0]].map(|t| t + 1);
        let header = serde_json::json!({"op": "step", "slots": slots, "payload": sent.len()});
        let (reply, values) = self.call(&header, &sent, self.step_timeout, &slots, step)?;
        let n = slots.len();
        let sizes = [reply.terminated.len(), reply.truncated.len(), reply.success.len()];
        if reply.slots != slots || values.len() != n * (od + 1) || sizes != [n; 3] {
            let why = format!(
                "step of environments {slots:?} answered environments {:?} with {} values \
                 ({od} per observation, then a reward each) and {sizes:?} flags",
                reply.slots,
                values.len()
            );
            return Err(self.malformed(&slots, step, why));
        }
        let (obs, rewards) = values.split_at(n * od);
        for (k, &slot) in slots.iter().enumerate() {
            let t = self.steps[slot].unwrap_or(0) + 1;
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
        Ok(out)
    }
}
