//! A trained run's prompted policy (`pdt_policy`) and the prompts it acts from.

use crate::errors::Failure;
use crate::prompts::{Adaptation, Prompt, TaskPlan};
use crate::{array2, existing, lib_error, lock, uint_arg, usize_arg, usize_list, value_error};
use numpy::{AllowTypeChange, PyArray2, PyArrayLike1, PyArrayLike2, PyArrayLikeDyn};
use pdt_model::PrefixCache;
use pdt_policy::{Episode, Inputs, PolicyError, PromptArrays, Target};
use pdt_prompt::SegmentBatch;
use pyo3::prelude::*;
use std::path::PathBuf;
use std::sync::Mutex;
use tch::Tensor;

/// A `bandit` prompt strategy over one task's candidate segments (docs/prompt-control.md): each
/// `choose()` gives the next episode's prompt, each `update(episode_return)` teaches it that
/// episode's return. Made by `Policy.prompt_bandit`.
#[pyclass(module = "promptdt._native", frozen)]
pub(crate) struct PromptBandit {
    policy: Py<Policy>,
    state: Mutex<BanditState>,
    /// The task whose prompts it chooses.
    #[pyo3(get)]
    task: usize,
}

struct BanditState {
    bandit: pdt_eval::testtime::TaskBandit,
    /// The arms of the prompt chosen last, until its return is reported.
    pending: Option<pdt_prompt::bandit::BanditChoice>,
}

#[pymethods]
impl PromptBandit {
    /// The next episode's prompt (its segments in `Prompt.segments`). A choice whose return was
    /// not reported is dropped.
    fn choose(&self, py: Python<'_>) -> PyResult<Prompt> {
        let policy = self.policy.bind(py).get();
        let st = lock(&policy.state)?;
        let mut b = lock(&self.state)?;
        let (chosen, choice) = st.run.bandit_prompt(&mut b.bandit).map_err(lib_error)?;
        b.pending = Some(choice);
        Ok(Prompt { inner: chosen.prompt, segments: chosen.segments })
    }

    /// The return of the episode acted with the prompt `choose()` gave last.
    fn update(&self, episode_return: f64) -> PyResult<()> {
        if !episode_return.is_finite() {
            return Err(value_error(format!("episode_return {episode_return} is not finite")));
        }
        let mut b = lock(&self.state)?;
        let choice = b.pending.take().ok_or_else(|| {
            value_error("update: no prompt chosen since the last update (call choose() first)")
        })?;
        b.bandit.update(&choice, episode_return);
        Ok(())
    }

    fn __repr__(&self) -> String {
        format!("PromptBandit(task={})", self.task)
    }
}

struct PolicyState {
    run: pdt_policy::Policy,
    /// The keys and values of the distinct prompts set (`None`: no prompt set), and the row of
    /// each episode (one row: every episode).
    prefix: Option<(PrefixCache, Vec<i64>)>,
    /// LoRA adapters every forward goes through (`set_prompt` of a LoRA `Adaptation`).
    lora: Option<pdt_model::LoraAdapters>,
    /// One per episode (its history, last action and checks); `None` until its first
    /// observation.
    episodes: Vec<Option<Episode>>,
    /// The return of each episode that `act`'s `done` ended, until its slot starts again.
    ended: Vec<Option<f64>>,
    /// The first return token of the episodes (`reset`'s target return).
    target: Target,
}

/// A trained run's prompted policy, acting in a batch of episodes as `promptdt eval` does.
#[pyclass(module = "promptdt._native", frozen)]
pub(crate) struct Policy {
    state: Mutex<PolicyState>,
    #[pyo3(get)]
    obs_dim: usize,
    #[pyo3(get)]
    act_dim: usize,
    /// History length K.
    #[pyo3(get)]
    k: usize,
    #[pyo3(get)]
    method: String,
    /// The run's environment family.
    #[pyo3(get)]
    env: String,
    #[pyo3(get)]
    uses_prompt: bool,
    #[pyo3(get)]
    target_return: f32,
    #[pyo3(get)]
    rtg_scale: f32,
    #[pyo3(get)]
    max_ep_len: usize,
    /// Iteration of the checkpoint loaded.
    #[pyo3(get)]
    iteration: u64,
    /// Steps of a prompt drawn from the run's data.
    #[pyo3(get)]
    prompt_steps: usize,
}

/// What `act` does with an episode: start it at its first observation, record its step, or end
/// it (`done`: its final reward is counted, and its next observation is a first one).
enum Next {
    Start(pdt_policy::Observation),
    Step(pdt_policy::Step),
    End(f64),
}

/// One value per episode of `n`: a scalar or an [n, 1] column is refused rather than broadcast.
fn per_episode(name: &str, shape: &[usize], n: usize) -> PyResult<()> {
    match shape {
        [m] if *m == n => Ok(()),
        [m] => Err(value_error(format!("{name}: {m} values for {n} episodes"))),
        _ => Err(value_error(format!("{name}: shape {shape:?}, expected [{n}] (one per episode)"))),
    }
}

impl PolicyState {
    /// What `act` does with each episode, every input checked before any episode changes, so an
    /// error leaves the state as it was.
    fn next_steps(
        &self,
        obs: numpy::ndarray::ArrayViewD<'_, f64>,
        reward: Option<&[f64]>,
        done: &[bool],
    ) -> PyResult<Vec<Next>> {
        let at = |i: usize| move |e: PolicyError| value_error(format!("episode {i}: {e}"));
        let mut steps = Vec::with_capacity(self.episodes.len());
        for (i, row) in obs.rows().into_iter().enumerate() {
            let o = self.run.observation(&row.to_vec()).map_err(at(i))?;
            let Some(e) = &self.episodes[i] else {
                if done[i] {
                    return Err(value_error(format!(
                        "done[{i}] is true, but episode {i} is at its first observation (an \
                         episode ends on a step after its first act)"
                    )));
                }
                steps.push(Next::Start(o));
                continue;
            };
            let Some(r) = reward.map(|r| r[i]) else {
                return Err(value_error(format!(
                    "episode {i} is under way: pass the rewards of the last actions"
                )));
            };
            let step = self.run.step(r, o).map_err(at(i))?;
            if done[i] {
                // Its final observation is not recorded: no action is taken from it.
                steps.push(Next::End(e.ret() + r));
                continue;
            }
            match self.run.check(e, &step) {
                Err(PolicyError::EpisodeFull { max_ep_len }) => {
                    return Err(value_error(format!(
                        "episode {i} has reached the model's max_ep_len ({max_ep_len} steps): reset or restart it"
                    )))
                }
                Err(e) => return Err(at(i)(e)),
                Ok(()) => steps.push(Next::Step(step)),
            }
        }
        Ok(steps)
    }

    /// Starts, steps and ends the episodes as `steps` say; returns the episodes ended, kept until
    /// the call is accepted.
    fn apply(&mut self, steps: Vec<Next>) -> PyResult<Vec<(usize, Episode)>> {
        let mut finished = Vec::new();
        for (i, next) in steps.into_iter().enumerate() {
            let slot = &mut self.episodes[i];
            let internal = || value_error(format!("internal: episode {i} has no state"));
            match next {
                Next::Start(o) => {
                    *slot = Some(self.run.start(o, self.target));
                    self.ended[i] = None;
                }
                Next::Step(step) => {
                    let e = slot.as_mut().ok_or_else(internal)?;
                    self.run.record(e, step).map_err(lib_error)?;
                }
                Next::End(ret) => {
                    finished.push((i, slot.take().ok_or_else(internal)?));
                    self.ended[i] = Some(ret);
                }
            }
        }
        Ok(finished)
    }

    /// Refuses a call whose action of episode `bad` is not finite: every episode goes back to
    /// where it was before the call (`flat`: the actions of the `active` episodes; `starts`: the
    /// episodes the call started; `finished`, `ended_before`: what it ended). Returns why.
    fn roll_back(
        &mut self,
        bad: usize,
        active: &[usize],
        flat: &[f32],
        starts: &[bool],
        finished: Vec<(usize, Episode)>,
        ended_before: Vec<Option<f64>>,
    ) -> String {
        let da = flat.len() / active.len().max(1);
        let mut why = None;
        for (&i, a) in active.iter().zip(flat.chunks_exact(da.max(1))) {
            let slot = &mut self.episodes[i];
            let Some(e) = slot else { continue };
            if i == bad {
                why = e.accept(a).err();
            } else {
                e.take_back();
            }
            // An episode started by this call is not started.
            if starts[i] {
                *slot = None;
            }
        }
        for (i, e) in finished {
            self.episodes[i] = Some(e);
        }
        self.ended = ended_before;
        why.map_or_else(String::new, |e| e.to_string())
    }
}

impl Policy {
    /// `set_prompt(adaptation)`: the adapted prompt's keys and values for every episode, and
    /// LoRA's adapters.
    fn set_adaptation(&self, a: &Adaptation) -> PyResult<()> {
        if a.policy != self as *const Policy as usize {
            return Err(value_error(
                "set_prompt: this Adaptation was made by another Policy; adapt with this one",
            ));
        }
        let mut st = lock(&self.state)?;
        if !st.run.method.uses_prompt() {
            return Err(value_error(format!(
                "this run's method ({}) takes no prompt",
                self.method
            )));
        }
        let adapted = lock(&a.inner)?;
        // One prompt's keys and values: milliseconds, so the GIL is kept.
        let cache = adapted.prefix(&st.run.model);
        st.lora = adapted.lora().map(pdt_model::LoraAdapters::shallow_clone);
        st.prefix = Some((cache, vec![0]));
        Ok(())
    }

    /// The prompt rows of the episodes `active` (indices among `n`).
    fn batch_prefix(st: &PolicyState, n: usize, active: &[usize]) -> PyResult<Option<PrefixCache>> {
        if !st.run.method.uses_prompt() {
            return Ok(None);
        }
        let Some((cache, rows)) = &st.prefix else {
            return Err(value_error("this run's method takes a prompt: call set_prompt first"));
        };
        let rows: Vec<i64> = match rows.len() {
            1 => vec![rows[0]; n],
            m if m == n => rows.clone(),
            m => {
                return Err(value_error(format!(
                    "{m} prompts were set for {n} episodes: give one prompt, or one per episode"
                )))
            }
        };
        let rows: Vec<i64> = active.iter().map(|&i| rows[i]).collect();
        let index = Tensor::from_slice(&rows).to_device(st.run.device);
        Ok(Some(cache.select(&index)))
    }
}

#[pymethods]
impl Policy {
    /// Loads the latest checkpoint of the run in `run_dir` (a directory `promptdt train` wrote).
    /// `device`: "cpu", "cuda", "cuda:N" or "auto"; `data`: where the run's data are now, if they
    /// moved (needed only for `task_prompt` and `eval_plan`); `threads`: libtorch threads (None:
    /// libtorch's default).
    #[staticmethod]
    #[pyo3(signature = (run_dir, device = "cpu", data = None, threads = None))]
    fn load(
        py: Python<'_>,
        run_dir: PathBuf,
        device: &str,
        data: Option<PathBuf>,
        threads: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        existing(&run_dir, "run directory")?;
        let device: pdt_base::device::DeviceSpec = device.parse().map_err(value_error)?;
        if let Some(t) = threads {
            let t = usize_arg("threads", t, "a number of libtorch threads")?;
            if t == 0 {
                return Err(value_error("threads: 0 given, expected at least 1"));
            }
            tch::set_num_threads(t as i32);
        }
        let run = py
            .detach(|| {
                pdt_policy::Policy::load(&run_dir, Some(device), data.as_deref())
                    .map_err(|e| Failure::of(&e))
            })
            .map_err(Failure::into_py)?;
        let target = run.target(None).map_err(lib_error)?;
        Ok(Self {
            obs_dim: run.stats.obs_dim,
            act_dim: run.stats.act_dim,
            k: run.k,
            method: run.method.name().to_string(),
            env: run.env.clone(),
            uses_prompt: run.method.uses_prompt(),
            target_return: run.stats.target_return,
            rtg_scale: run.stats.rtg_scale,
            max_ep_len: run.max_ep_len(),
            iteration: run.iteration,
            prompt_steps: run.prompt_steps,
            state: Mutex::new(PolicyState {
                run,
                prefix: None,
                lora: None,
                episodes: Vec::new(),
                ended: Vec::new(),
                target,
            }),
        })
    }

    /// The tasks whose prompts `task_prompt` can draw (test tasks first).
    fn prompt_tasks(&self) -> PyResult<Vec<usize>> {
        lock(&self.state)?.run.prompt_tasks().map_err(lib_error)
    }

    /// A prompt of task `task` drawn from the run's prompt set as the evaluation draws one (`seed`:
    /// None is 0). `prompt_strategy` (docs/prompt-control.md): `reference` (default),
    /// `random-segment`, `best-return` or `nearest-start` (nearest `observation`, the episode's
    /// raw first observation); `prompt_episodes` / `prompt_length`: the test-time J and H.
    #[pyo3(signature = (task, seed = None, prompt_strategy = None, observation = None,
                        prompt_episodes = None, prompt_length = None))]
    fn task_prompt(
        &self,
        task: &Bound<'_, PyAny>,
        seed: Option<&Bound<'_, PyAny>>,
        prompt_strategy: Option<&str>,
        observation: Option<PyArrayLike1<'_, f32, AllowTypeChange>>,
        prompt_episodes: Option<&Bound<'_, PyAny>>,
        prompt_length: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Prompt> {
        let task = usize_arg("task", task, "a task index of the run's family")?;
        let seed =
            seed.map(|s| uint_arg("seed", s, "a seed in [0, 2**64)")).transpose()?.unwrap_or(0);
        let count = |name: &str, v: Option<&Bound<'_, PyAny>>| {
            v.map(|v| usize_arg(name, v, "a number of prompt steps (at least 1)")).transpose()
        };
        let strategy = pdt_prompt::PromptStrategy {
            strategy: prompt_strategy.unwrap_or("reference").parse().map_err(lib_error)?,
            episodes: count("prompt_episodes", prompt_episodes)?,
            length: count("prompt_length", prompt_length)?,
            ..Default::default()
        };
        let obs: Option<Vec<f32>> = observation.map(|o| o.as_array().to_vec());
        let st = lock(&self.state)?;
        if strategy.is_default() {
            let inner = st.run.task_prompt(task, seed).map_err(lib_error)?;
            return Ok(Prompt { inner, segments: vec![] });
        }
        if let Some(o) = &obs {
            st.run
                .observation(&o.iter().map(|&x| f64::from(x)).collect::<Vec<_>>())
                .map_err(lib_error)?;
        }
        let chosen =
            st.run.strategy_prompt(task, seed, &strategy, obs.as_deref()).map_err(lib_error)?;
        Ok(Prompt { inner: chosen.prompt, segments: chosen.segments })
    }

    /// A `bandit` prompt strategy over task `task`'s candidate segments, its choices seeded by
    /// `seed` (None is 0): `rule` `"epsilon-greedy"` (default) or `"ucb"`, `epsilon` (0.1),
    /// `prompt_episodes` / `prompt_length` the test-time J and H, `stride` the candidates' step
    /// (default H).
    #[pyo3(signature = (task, seed = None, rule = None, epsilon = None, prompt_episodes = None,
                        prompt_length = None, stride = None))]
    #[allow(clippy::too_many_arguments)] // the keywords of a Python method
    fn prompt_bandit(
        slf: &Bound<'_, Self>,
        task: &Bound<'_, PyAny>,
        seed: Option<&Bound<'_, PyAny>>,
        rule: Option<&str>,
        epsilon: Option<f64>,
        prompt_episodes: Option<&Bound<'_, PyAny>>,
        prompt_length: Option<&Bound<'_, PyAny>>,
        stride: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<PromptBandit> {
        let task = usize_arg("task", task, "a task index of the run's family")?;
        let seed =
            seed.map(|s| uint_arg("seed", s, "a seed in [0, 2**64)")).transpose()?.unwrap_or(0);
        let count = |name: &str, v: Option<&Bound<'_, PyAny>>| {
            v.map(|v| usize_arg(name, v, "a number of steps (at least 1)")).transpose()
        };
        let d = pdt_prompt::BanditConfig::default();
        let rule = match rule {
            None | Some("epsilon-greedy") => pdt_prompt::BanditRule::EpsilonGreedy,
            Some("ucb") => pdt_prompt::BanditRule::Ucb,
            Some(other) => {
                return Err(value_error(format!(
                    "unknown bandit rule `{other}` (known: epsilon-greedy, ucb)"
                )))
            }
        };
        let strategy = pdt_prompt::PromptStrategy {
            strategy: pdt_prompt::PromptStrategyKind::Bandit,
            episodes: count("prompt_episodes", prompt_episodes)?,
            length: count("prompt_length", prompt_length)?,
            stride: count("stride", stride)?,
            bandit: pdt_prompt::BanditConfig { rule, epsilon: epsilon.unwrap_or(d.epsilon), ..d },
        };
        strategy.validate().map_err(lib_error)?;
        let bandit = {
            let st = lock(&slf.get().state)?;
            st.run.task_bandit(task, seed, &strategy).map_err(lib_error)?
        };
        Ok(PromptBandit {
            policy: slf.clone().unbind(),
            state: Mutex::new(BanditState { bandit, pending: None }),
            task,
        })
    }

    /// A prompt from a demonstration's arrays: raw states `[n, obs_dim]`, actions `[n, act_dim]`,
    /// raw returns-to-go `[n]` (not divided by the scale) and timesteps `[n]`.
    fn prompt(
        &self,
        states: PyArrayLike2<'_, f64, AllowTypeChange>,
        actions: PyArrayLike2<'_, f64, AllowTypeChange>,
        returns_to_go: PyArrayLike1<'_, f64, AllowTypeChange>,
        timesteps: PyArrayLike1<'_, i64, AllowTypeChange>,
    ) -> PyResult<Prompt> {
        let rows = |a: &PyArrayLike2<'_, f64, AllowTypeChange>| -> Vec<Vec<f64>> {
            a.as_array().rows().into_iter().map(|r| r.to_vec()).collect()
        };
        let arrays = PromptArrays {
            states: rows(&states),
            actions: rows(&actions),
            returns_to_go: returns_to_go.as_array().to_vec(),
            timesteps: timesteps.as_array().to_vec(),
        };
        let st = lock(&self.state)?;
        // The prompt's largest inputs are not kept: an episode names its own when its action is
        // refused.
        let mut inputs = Inputs::default();
        let inner = st.run.prompt_from_arrays(&arrays, &mut inputs).map_err(lib_error)?;
        Ok(Prompt { inner, segments: vec![] })
    }

    /// What `promptdt eval --split SPLIT --episodes N` draws for each task, in its order. Acting
    /// on all of them together (one environment per seed, task by task, each episode with its
    /// task's prompt) takes the evaluation's actions and returns.
    #[pyo3(signature = (split = "test", episodes = None))]
    fn eval_plan(
        &self,
        py: Python<'_>,
        split: &str,
        episodes: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Vec<TaskPlan>> {
        let episodes = episodes
            .map(|e| usize_arg("episodes", e, "a number of episodes per task"))
            .transpose()?;
        let plan = lock(&self.state)?.run.eval_plan(split, episodes).map_err(lib_error)?;
        plan.into_iter()
            .map(|t| {
                let prompt = t
                    .prompt
                    .map(|p| Py::new(py, Prompt { inner: p, segments: vec![] }))
                    .transpose()?;
                Ok(TaskPlan { name: t.name, index: t.index, seeds: t.seeds, prompt })
            })
            .collect()
    }

    /// Sets the prompt: one `Prompt` for every episode, or a list with one per episode. The
    /// distinct prompts' keys and values are computed once, together, as the evaluator does.
    /// An `Adaptation` (`Policy.adapt`) sets its task's adapted prompt (and LoRA's adapters) for
    /// every episode.
    fn set_prompt(&self, py: Python<'_>, prompt: &Bound<'_, PyAny>) -> PyResult<()> {
        if let Ok(a) = prompt.cast::<Adaptation>() {
            return self.set_adaptation(a.get());
        }
        let items: Vec<Bound<'_, Prompt>> = match prompt.cast::<Prompt>() {
            Ok(p) => vec![p.clone()],
            Err(_) => prompt.extract().map_err(|_| {
                value_error("set_prompt takes a Prompt or a list of Prompts (one per episode)")
            })?,
        };
        if items.is_empty() {
            return Err(value_error("set_prompt: the list of prompts is empty"));
        }
        // Distinct prompt objects, in order of first appearance, and each episode's row.
        let mut distinct: Vec<&Bound<'_, Prompt>> = Vec::new();
        let mut rows = Vec::with_capacity(items.len());
        for p in &items {
            let row = match distinct.iter().position(|d| d.is(p)) {
                Some(r) => r,
                None => {
                    distinct.push(p);
                    distinct.len() - 1
                }
            };
            rows.push(row as i64);
        }
        let batches: Vec<&SegmentBatch> = distinct.iter().map(|p| &p.get().inner).collect();
        let mut st = lock(&self.state)?;
        if !st.run.method.uses_prompt() {
            return Err(value_error(format!(
                "this run's method ({}) takes no prompt",
                self.method
            )));
        }
        if let Some(b) =
            batches.iter().find(|b| b.state_dim != self.obs_dim || b.act_dim != self.act_dim)
        {
            return Err(value_error(format!(
                "prompt dims {}/{} differ from the policy's {}/{}",
                b.state_dim, b.act_dim, self.obs_dim, self.act_dim
            )));
        }
        // `&mut` to hand the (Send, not Sync) policy to the GIL-free closure.
        let run = &mut st.run;
        let cache = py
            .detach(move || run.prefix(&batches).map_err(|e| Failure::of(&e)))
            .map_err(Failure::into_py)?;
        st.prefix = Some((cache, rows));
        st.lora = None;
        Ok(())
    }

    /// Adapts to task `task` from its demonstrations, the backbone frozen
    /// (docs/prompt-control.md): `adapt` is `soft-prompt`, `ptdt` or `lora`; it starts from the
    /// prompt `prompt_strategy` picks (`reference`, `random-segment` or `best-return`; `seed`
    /// seeds that draw and the adaptation, None is 0). `steps`, `batch`, `lr`: the budget
    /// (defaults 20, 16, 1e-3, as `[eval.adapt]`). Returns an `Adaptation`; act with it through
    /// `set_prompt`.
    #[pyo3(signature = (task, adapt, seed = None, prompt_strategy = None, steps = None,
                        batch = None, lr = None))]
    #[allow(clippy::too_many_arguments)] // the keywords of `Policy.adapt`
    fn adapt(
        slf: &Bound<'_, Self>,
        py: Python<'_>,
        task: &Bound<'_, PyAny>,
        adapt: &str,
        seed: Option<&Bound<'_, PyAny>>,
        prompt_strategy: Option<&str>,
        steps: Option<&Bound<'_, PyAny>>,
        batch: Option<&Bound<'_, PyAny>>,
        lr: Option<f64>,
    ) -> PyResult<Adaptation> {
        let task = usize_arg("task", task, "a task index of the run's family")?;
        let seed =
            seed.map(|s| uint_arg("seed", s, "a seed in [0, 2**64)")).transpose()?.unwrap_or(0);
        let mut cfg = pdt_rundir::config::AdaptConfig {
            kind: adapt.parse().map_err(lib_error)?,
            ..Default::default()
        };
        if cfg.kind == pdt_rundir::config::AdaptKind::None {
            return Err(value_error("adapt: name an adaptation (soft-prompt, ptdt, lora)"));
        }
        if let Some(s) = steps {
            cfg.steps = usize_arg("steps", s, "adaptation iterations")?;
        }
        if let Some(b) = batch {
            cfg.batch = usize_arg("batch", b, "demonstration segments per iteration")?;
        }
        cfg.lr = lr.unwrap_or(cfg.lr);
        let strategy = pdt_prompt::PromptStrategy {
            strategy: prompt_strategy.unwrap_or("reference").parse().map_err(lib_error)?,
            ..Default::default()
        };
        let adaptation = pdt_rundir::config::Adaptation::Prompt(cfg);
        let test_time = pdt_rundir::config::TestTime::Adapt { from: strategy, adaptation };
        let mut st = lock(&slf.get().state)?;
        // `&mut` to hand the (Send, not Sync) policy to the GIL-free closure.
        let run = &mut st.run;
        let a = py
            .detach(move || run.adapt(task, seed, &test_time).map_err(|e| Failure::of(&e)))
            .map_err(Failure::into_py)?;
        drop(st);
        let policy = slf.get() as *const Policy as usize;
        let owner = slf.clone().into_any().unbind();
        Ok(Adaptation {
            kind: adapt.to_string(),
            task,
            inner: Mutex::new(a),
            policy,
            _owner: owner,
        })
    }

    /// Starts `n_episodes` new episodes (the next `act` takes their first observations), aiming
    /// at `target_return` (None: the run's G*).
    #[pyo3(signature = (n_episodes, target_return = None))]
    fn reset(&self, n_episodes: &Bound<'_, PyAny>, target_return: Option<f64>) -> PyResult<()> {
        let n_episodes = usize_arg("n_episodes", n_episodes, "a number of episodes")?;
        if n_episodes == 0 {
            return Err(value_error("n_episodes: 0 given, expected at least 1"));
        }
        let mut st = lock(&self.state)?;
        st.target = st.run.target(target_return).map_err(lib_error)?;
        st.episodes = vec![None; n_episodes];
        st.ended = vec![None; n_episodes];
        Ok(())
    }

    /// Restarts the given episodes (e.g. those an environment reset): their next observation is
    /// a first one.
    fn restart(&self, episodes: &Bound<'_, PyAny>) -> PyResult<()> {
        let mut st = lock(&self.state)?;
        let n = st.episodes.len();
        let episodes = usize_list("episodes", episodes, &format!("an episode index (0..{n})"))?;
        if let Some(i) = episodes.iter().find(|&&i| i >= n) {
            return Err(value_error(format!(
                "episodes: episode {i} given, expected an episode index (0..{n})"
            )));
        }
        for &i in &episodes {
            st.episodes[i] = None;
            st.ended[i] = None;
        }
        Ok(())
    }

    /// The next action of every episode, `[n, act_dim]` float32. `obs`: `[n, obs_dim]` raw
    /// observations; `reward`: `[n]`, the rewards the last actions earned (ignored for episodes at
    /// their first observation, required for the others); `done`: `[n]` bool, the episodes that
    /// ended with this step (a gymnasium env's `terminated | truncated`). An episode that is done
    /// counts its reward and ends: its row of the result is zeros (a NEXT_STEP-autoreset env
    /// ignores it), and its next observation is the first of a new episode, as after `restart`.
    #[pyo3(signature = (obs, reward = None, done = None))]
    fn act<'py>(
        &self,
        py: Python<'py>,
        obs: PyArrayLikeDyn<'py, f64, AllowTypeChange>,
        reward: Option<PyArrayLikeDyn<'py, f64, AllowTypeChange>>,
        done: Option<PyArrayLikeDyn<'py, bool, AllowTypeChange>>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let obs = obs.as_array();
        let mut guard = lock(&self.state)?;
        let st = &mut *guard;
        let n = st.episodes.len();
        if n == 0 {
            return Err(value_error("call reset(n_episodes) before act"));
        }
        if obs.shape() != [n, self.obs_dim] {
            return Err(value_error(format!(
                "obs: shape {:?}, expected [{n}, {}] (episodes, obs_dim)",
                obs.shape(),
                self.obs_dim
            )));
        }
        let reward: Option<Vec<f64>> = match reward {
            Some(r) => {
                let r = r.as_array();
                per_episode("reward", r.shape(), n)?;
                Some(r.iter().copied().collect())
            }
            None => None,
        };
        let done: Vec<bool> = match done {
            Some(d) => {
                let d = d.as_array();
                per_episode("done", d.shape(), n)?;
                d.iter().copied().collect()
            }
            None => vec![false; n],
        };
        let steps = st.next_steps(obs, reward.as_deref(), &done)?;
        let starts: Vec<bool> = steps.iter().map(|s| matches!(s, Next::Start(_))).collect();
        let active: Vec<usize> = (0..n).filter(|&i| !done[i]).collect();
        let prefix = if active.is_empty() { None } else { Self::batch_prefix(st, n, &active)? };
        let ended_before = st.ended.clone();
        let finished = st.apply(steps)?;
        let flat = if active.is_empty() {
            Vec::new()
        } else {
            // `&mut` to hand the (Send, not Sync) policy to the GIL-free closure.
            let st: &mut PolicyState = st;
            py.detach(move || {
                let eps: Vec<&Episode> = st.episodes.iter().flatten().collect();
                st.run.act_with(&eps, prefix.as_ref(), st.lora.as_ref()) // [active * da]
            })
        };
        let da = self.act_dim;
        // An action that is not finite (inputs each representable can still overflow inside the
        // model) refuses the whole call: every episode goes back to where it was before it.
        if let Some(b) = flat.chunks_exact(da).position(|a| a.iter().any(|x| !x.is_finite())) {
            let b = active[b];
            let why = st.roll_back(b, &active, &flat, &starts, finished, ended_before);
            return Err(value_error(format!(
                "episode {b}: {why}. The call is refused and every episode is as it was before it"
            )));
        }
        let mut out = vec![0f32; n * da];
        for (&i, a) in active.iter().zip(flat.chunks_exact(da)) {
            if let Some(e) = &mut st.episodes[i] {
                e.accept(a).map_err(lib_error)?;
            }
            out[i * da..(i + 1) * da].copy_from_slice(a);
        }
        array2(py, out, n, da)
    }

    /// Returns so far of each episode: None before its first observation; the final return of an
    /// episode `act`'s `done` ended, until its next observation starts a new one.
    fn episode_returns(&self) -> PyResult<Vec<Option<f64>>> {
        let st = lock(&self.state)?;
        Ok(st
            .episodes
            .iter()
            .zip(&st.ended)
            .map(|(e, ended)| e.as_ref().map(Episode::ret).or(*ended))
            .collect())
    }

    fn __repr__(&self) -> String {
        format!(
            "Policy(method={:?}, env={:?}, obs_dim={}, act_dim={}, k={}, iteration={})",
            self.method, self.env, self.obs_dim, self.act_dim, self.k, self.iteration
        )
    }
}
