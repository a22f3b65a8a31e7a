//! A task suite read from a TOML file: a user's task family, declared rather than coded.
//!
//! A suite declares what a built-in family declares in code (sizes, action bounds, horizon,
//! return-to-go scale, target returns, prompt length, tasks with their parameters, named splits,
//! optionally a success reward, per-task expert/random returns and the `[environment]` a Python
//! worker makes), and is an [`EnvFamily`] like the built-in ones: [`crate::family`] takes the path
//! of a suite file (any name ending in `.toml`) wherever it takes a family name. Every field is
//! checked when the file is read, each error naming the file, the field and why
//! (`docs/your-own-tasks.md` documents the fields).
//!
//! A suite's environment is never stepped in this process: [`EnvFamily::make`] refuses, and
//! evaluation in the user's environment goes through the Python worker ([`crate::worker`]).

mod check;
mod file;

use crate::vec_env::{EnvDims, VecEnv};
use crate::worker::{WorkerSpec, WorkerTask};
use crate::{ActionBounds, Env, EnvError, EnvFamily, EnvPreset};
use std::path::{Path, PathBuf};

/// The largest suite file read (a suite of thousands of tasks is a few hundred kB).
const MAX_FILE_BYTES: u64 = 16 << 20;

/// A suite file that cannot be used, naming the file and (for a bad field) the field and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SuiteError {
    #[error("suite file {}: cannot read it: {message}", path.display())]
    Read { path: PathBuf, message: String },
    /// Not TOML, or a top-level field missing, unknown or of the wrong type (toml's message names
    /// the field and the line).
    #[error("suite file {}: {message}", path.display())]
    Syntax { path: PathBuf, message: String },
    #[error("suite file {}: `{field}` {why}", path.display())]
    Field { path: PathBuf, field: String, why: String },
    /// The suite file a run was trained on was edited since: the run's copy and the file differ.
    #[error(
        "suite file {} changed since the run was trained on it (the run keeps the suite it trained \
         on in {}): restore the file, or move it away to use the run's copy",
        path.display(),
        copy.display()
    )]
    Changed { path: PathBuf, copy: PathBuf },
}

/// One task of a suite.
#[derive(Debug, Clone, PartialEq)]
pub struct SuiteTask {
    pub name: String,
    /// The `params` table, as JSON (what dataset cards record and the worker receives).
    pub params: serde_json::Value,
    /// The task's own target return G*, if it has one (else the suite's).
    pub target_return: Option<f32>,
    /// `(expert_return, random_return)` that normalise this task's scores, if given.
    pub reference: Option<(f64, f64)>,
}

/// One named split: task indices trained on and held out.
#[derive(Debug, Clone, PartialEq)]
pub struct SuiteSplit {
    pub name: String,
    pub train: Vec<usize>,
    pub test: Vec<usize>,
}

/// A checked suite file ([`SuiteFamily::load`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SuiteFamily {
    path: PathBuf,
    /// The file's text as read: what a run directory keeps a copy of.
    text: String,
    name: String,
    preset: EnvPreset,
    bounds: ActionBounds,
    render_fps: Option<u32>,
    success_reward: Option<f32>,
    tasks: Vec<SuiteTask>,
    splits: Vec<SuiteSplit>,
    environment: Option<WorkerSpec>,
}

/// Whether [`crate::family`] reads `name` as the path of a suite file: it ends in `.toml`. A rule
/// on the name alone (not "an existing file") so that a mistyped path is reported as a missing
/// suite file, never as an unknown family, and a built-in family is never shadowed by a file.
pub fn is_suite_path(name: &str) -> bool {
    name.ends_with(".toml")
}

impl SuiteFamily {
    /// Reads and checks the suite file at `path`.
    pub fn load(path: &Path) -> Result<Self, SuiteError> {
        let read_err = |message: String| SuiteError::Read { path: path.to_path_buf(), message };
        let text = pdt_base::fs::read_limited(path, MAX_FILE_BYTES)
            .map_err(|e| read_err(e.to_string()))?;
        let text = String::from_utf8(text).map_err(|_| read_err("not UTF-8 text".into()))?;
        Self::parse(path, text)
    }

    /// Checks `text` as the suite file at `path` (relative paths inside resolve against its
    /// directory; errors name it).
    pub fn parse(path: &Path, text: String) -> Result<Self, SuiteError> {
        let raw: file::RawSuite = toml::from_str(&text).map_err(|e| SuiteError::Syntax {
            path: path.to_path_buf(),
            message: e.to_string().trim_end().to_owned(),
        })?;
        check::check(path, text, raw)
    }

    /// The suite a run was trained on: `copy` is the run's copy of the file at `path` (the path
    /// its configuration records). The copy is what is read, so a run evaluates, serves and
    /// resumes without the original; relative paths inside still resolve against `path`'s
    /// directory. An original that still exists must be unchanged ([`SuiteError::Changed`]):
    /// an edited suite (tasks renamed, splits changed) silently used with the run's weights
    /// and data would give numbers of another experiment.
    pub fn as_trained(path: &Path, copy: &Path) -> Result<Self, SuiteError> {
        let read = |p: &Path| -> Result<String, SuiteError> {
            let bytes = pdt_base::fs::read_limited(p, MAX_FILE_BYTES)
                .map_err(|e| SuiteError::Read { path: p.to_path_buf(), message: e.to_string() })?;
            String::from_utf8(bytes).map_err(|_| SuiteError::Read {
                path: p.to_path_buf(),
                message: "not UTF-8 text".into(),
            })
        };
        let text = read(copy)?;
        if path.exists() && read(path)? != text {
            return Err(SuiteError::Changed { path: path.to_path_buf(), copy: copy.to_path_buf() });
        }
        Self::parse(path, text)
    }

    /// The file this suite was read from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file's text as read.
    pub fn text(&self) -> &str {
        &self.text
    }

    pub fn tasks(&self) -> &[SuiteTask] {
        &self.tasks
    }

    pub fn splits(&self) -> &[SuiteSplit] {
        &self.splits
    }

    /// The index of the task named `name`.
    pub fn task_index(&self, name: &str) -> Option<usize> {
        self.tasks.iter().position(|t| t.name == name)
    }

    /// The `[environment]` table, if the suite declares one.
    pub fn environment(&self) -> Option<&WorkerSpec> {
        self.environment.as_ref()
    }

    /// What a worker needs to make task `task`'s environment.
    pub fn worker_task(&self, task: usize) -> Result<WorkerTask, EnvError> {
        let t = self.task(task)?;
        Ok(WorkerTask { index: task, name: t.name.clone(), params: t.params.clone() })
    }

    fn task(&self, task: usize) -> Result<&SuiteTask, EnvError> {
        EnvError::check_task(&self.name, task, self.tasks.len())?;
        Ok(&self.tasks[task])
    }
}

impl EnvFamily for SuiteFamily {
    fn name(&self) -> &str {
        &self.name
    }

    fn num_tasks(&self) -> usize {
        self.tasks.len()
    }

    fn preset(&self) -> EnvPreset {
        self.preset.clone()
    }

    fn split_names(&self) -> Vec<String> {
        self.splits.iter().map(|s| s.name.clone()).collect()
    }

    /// A split by its name; `default` is the first declared split when none is named so (the
    /// name configurations use when they name none).
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        let found = self.splits.iter().find(|s| s.name == name).or_else(|| match name {
            "default" => self.splits.first(),
            _ => None,
        });
        match found {
            Some(s) => Ok((s.train.clone(), s.test.clone())),
            None => {
                let known: Vec<&str> = self.splits.iter().map(|s| s.name.as_str()).collect();
                Err(EnvError::unknown_split(&self.name, name, &known))
            }
        }
    }

    /// `{"name": ..., "params": {...}}`: the task's name and its `params` table.
    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        let t = self.task(task)?;
        Ok(serde_json::json!({ "name": t.name, "params": t.params }))
    }

    /// Always an error: a suite's environment is a user's Python environment, made and stepped by
    /// the worker process, never in this process.
    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        self.task(task)?;
        Err(EnvError::Unsupported {
            env: self.name.clone(),
            what: match self.environment {
                Some(_) => {
                    "in-process environment (the suite's [environment] runs in a Python worker)"
                }
                None => "environment (the suite declares no [environment]: a run trains without evaluations)",
            },
        })
    }

    /// The episodes' environments in one Python worker process (the suite's `[environment]`),
    /// one message per vector step ([`crate::worker::make_batch`]); refused as [`Self::make`]
    /// refuses when the suite declares no environment.
    fn make_batch(&self, tasks: &[usize], _threads: usize) -> Result<VecEnv, EnvError> {
        let Some(spec) = &self.environment else {
            return Err(EnvError::Unsupported {
                env: self.name.clone(),
                what: "environment (the suite declares no [environment]: a run trains without \
                       evaluations)",
            });
        };
        let slots = tasks.iter().map(|&t| self.worker_task(t)).collect::<Result<Vec<_>, _>>()?;
        let p = &self.preset;
        let dims = EnvDims { obs_dim: p.obs_dim, act_dim: p.act_dim, horizon: p.horizon };
        let dir = self.path.parent().unwrap_or(Path::new("."));
        crate::worker::make_batch(spec, dir, slots, dims)
    }

    /// The suite's `render_fps`, else 30 (what a video of its episodes plays at).
    fn render_fps(&self) -> u32 {
        self.render_fps.unwrap_or(30)
    }

    fn action_bounds(&self) -> ActionBounds {
        self.bounds.clone()
    }

    fn success_reward(&self) -> Option<f32> {
        self.success_reward
    }

    fn task_target_return(&self, task: usize) -> Option<f32> {
        self.tasks.get(task).and_then(|t| t.target_return)
    }

    fn reference_returns(&self, task: usize) -> Option<(f64, f64)> {
        self.tasks.get(task).and_then(|t| t.reference)
    }

    fn as_suite(&self) -> Option<&SuiteFamily> {
        Some(self)
    }
}
