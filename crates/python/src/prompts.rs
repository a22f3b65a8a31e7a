//! The prompt-side objects of the Python package: a `Prompt` (as the policy feeds it), a
//! `TaskPlan` (what `promptdt eval` draws for a task) and an `Adaptation` (a task adapted from its
//! demonstrations, `Policy.adapt`).

use crate::{array2, lock};
use numpy::prelude::*;
use numpy::{PyArray1, PyArray2};
use pdt_prompt::SegmentBatch;
use pyo3::prelude::*;
use std::sync::Mutex;

/// A prompt, as the policy feeds it: states normalised with the run's statistics, returns-to-go
/// divided by its scale. Made by `Policy.task_prompt`, `Policy.prompt` or `Policy.eval_plan`.
#[pyclass(module = "promptdt._native", frozen)]
pub(crate) struct Prompt {
    pub(crate) inner: SegmentBatch,
    /// The demonstration segments a prompt strategy chose (empty otherwise).
    pub(crate) segments: Vec<pdt_prompt::SegmentChoice>,
}

#[pymethods]
impl Prompt {
    /// Steps in the prompt (J x H).
    #[getter]
    fn steps(&self) -> usize {
        self.inner.steps
    }
    /// `[steps, obs_dim]` float32, normalised.
    #[getter]
    fn states<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let b = &self.inner;
        array2(py, b.states.clone(), b.steps, b.state_dim)
    }
    /// `[steps, act_dim]` float32.
    #[getter]
    fn actions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let b = &self.inner;
        array2(py, b.actions.clone(), b.steps, b.act_dim)
    }
    /// `[steps]` float32, divided by the run's return scale.
    #[getter]
    fn returns_to_go<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        self.inner.returns_to_go.clone().into_pyarray(py)
    }
    /// `[steps]` int64.
    #[getter]
    fn timesteps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        self.inner.timesteps.clone().into_pyarray(py)
    }
    /// `[steps]` float32: 1 for real steps, 0 for padding.
    #[getter]
    fn mask<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        self.inner.mask.clone().into_pyarray(py)
    }
    /// The segments a prompt strategy (`task_prompt(prompt_strategy=...)`) made the prompt of,
    /// in order: `{"demo": index in the task's prompt set, "start": first step}`; empty for the
    /// reference draw and array prompts.
    #[getter]
    fn segments(&self) -> Vec<std::collections::BTreeMap<&'static str, usize>> {
        self.segments
            .iter()
            .map(|c| [("demo", c.demo), ("start", c.start)].into_iter().collect())
            .collect()
    }
    fn __repr__(&self) -> String {
        format!(
            "Prompt(steps={}, obs_dim={}, act_dim={})",
            self.inner.steps, self.inner.state_dim, self.inner.act_dim
        )
    }
}

/// What `promptdt eval` draws for one task: the prompt its episodes share and their reset seeds.
#[pyclass(module = "promptdt._native", frozen, get_all)]
pub(crate) struct TaskPlan {
    /// `cheetah_vel-2`
    pub(crate) name: String,
    /// The task's index in its family.
    pub(crate) index: usize,
    /// Reset seed of each episode.
    pub(crate) seeds: Vec<u64>,
    /// None for the methods without a prompt.
    pub(crate) prompt: Option<Py<Prompt>>,
}

#[pymethods]
impl TaskPlan {
    fn __repr__(&self) -> String {
        format!(
            "TaskPlan(name={:?}, index={}, episodes={})",
            self.name,
            self.index,
            self.seeds.len()
        )
    }
}

/// A test task adapted from its demonstrations (`Policy.adapt`; docs/prompt-control.md): act
/// with it through `Policy.set_prompt(adaptation)`.
#[pyclass(module = "promptdt._native", frozen)]
pub(crate) struct Adaptation {
    /// `soft-prompt`, `ptdt` or `lora`.
    #[pyo3(get)]
    pub(crate) kind: String,
    /// The task adapted to.
    #[pyo3(get)]
    pub(crate) task: usize,
    pub(crate) inner: Mutex<pdt_eval::testtime::TaskAdaptation>,
    /// The `Policy` that made it (its address): its tensors fit that model only.
    pub(crate) policy: usize,
    /// That `Policy`, kept alive while the adaptation is, so no other takes its address.
    pub(crate) _owner: Py<PyAny>,
}

#[pymethods]
impl Adaptation {
    /// What the adaptation did: `{"task", "loss_before", "loss_after", "steps", "trainable",
    /// "seconds"}` (the demonstrations' probe action loss before and after, values adapted).
    #[getter]
    fn log<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyDict>> {
        let a = lock(&self.inner)?;
        let l = &a.log;
        let d = pyo3::types::PyDict::new(py);
        d.set_item("task", &l.task)?;
        d.set_item("loss_before", l.loss_before)?;
        d.set_item("loss_after", l.loss_after)?;
        d.set_item("steps", l.steps)?;
        d.set_item("trainable", l.trainable)?;
        d.set_item("seconds", l.seconds)?;
        Ok(d)
    }
    fn __repr__(&self) -> String {
        format!("Adaptation(kind={:?}, task={})", self.kind, self.task)
    }
}
