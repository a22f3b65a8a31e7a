//! Flat step arrays with a task column (what Python's `promptdt.flat_dataset` writes and offline
//! RL libraries take: `observations`, `actions`, `rewards`, `terminals`, `timeouts`, `task_ids`)
//! cut back into one [`TaskDataset`] per task, every array checked first; and the prompt sets
//! made from a task's data by the named rule [`PromptRule`].

use crate::{DataError, TaskDataset, Trajectory};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Every step of a multi-task dataset in flat, row-major arrays: step `i` belongs to task
/// `task_ids[i]`; an episode ends at a step whose `terminals` or `timeouts` is set.
#[derive(Debug, Clone, PartialEq)]
pub struct FlatSteps {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// `[N * obs_dim]`: the observation before `actions[i]`.
    pub observations: Vec<f32>,
    /// `[N * act_dim]`.
    pub actions: Vec<f32>,
    /// `[N]`.
    pub rewards: Vec<f32>,
    /// `[N]`: the MDP ended after step `i`.
    pub terminals: Vec<bool>,
    /// `[N]`: a time limit cut the episode after step `i`.
    pub timeouts: Vec<bool>,
    /// `[N]`: the task of step `i`.
    pub task_ids: Vec<i64>,
}

/// How a task's prompt set P_i is made from its data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PromptRule {
    /// The `n` episodes of highest return, whole and best first (the reference's prompt files
    /// are 5 whole expert episodes; the sampler takes the last H steps of one).
    BestReturn { episodes: usize },
}

impl std::str::FromStr for PromptRule {
    type Err = String;

    /// `best:N` (e.g. `best:5`).
    fn from_str(s: &str) -> Result<Self, String> {
        let n = s.strip_prefix("best:").and_then(|n| n.parse::<usize>().ok()).filter(|n| *n > 0);
        match n {
            Some(episodes) => Ok(PromptRule::BestReturn { episodes }),
            None => {
                Err(format!("unknown prompt rule {s:?}; expected best:N (N >= 1), e.g. best:5"))
            }
        }
    }
}

impl PromptRule {
    /// The prompt set of `data` by this rule.
    pub fn prompts(&self, data: &TaskDataset) -> TaskDataset {
        let trajectories =
            self.pick(&data.returns()).into_iter().map(|i| data.trajectories[i].clone()).collect();
        TaskDataset { obs_dim: data.obs_dim, act_dim: data.act_dim, trajectories }
    }

    /// Which episodes (indices into `returns`, one per episode) make the prompt set, in its order.
    pub fn pick(&self, returns: &[f64]) -> Vec<usize> {
        let PromptRule::BestReturn { episodes } = *self;
        let mut order: Vec<(f64, usize)> =
            returns.iter().copied().enumerate().map(|(i, r)| (r, i)).collect();
        // Highest return first; equal returns in file order.
        order.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        order.into_iter().take(episodes).map(|(_, i)| i).collect()
    }
}

/// Checks one array of a flat file against the shape its field must have: `[N, width]` for
/// observations and actions (`width`: `Some`), `[N]` or `[N, 1]` for a per-step column (`None`).
/// One rule for every flat format (`.npz`, HDF5); `path` and `field` name the error.
pub fn check_column_shape(
    path: &Path,
    field: &str,
    shape: &[u64],
    width: Option<usize>,
) -> Result<(), DataError> {
    let ok = match (width, shape) {
        (Some(w), [_, d]) => *d as usize == w,
        (None, [_]) | (None, [_, 1]) => true,
        _ => false,
    };
    if ok {
        return Ok(());
    }
    let want = width.map_or("[N]".to_owned(), |w| format!("[N, {w}]"));
    Err(bad(path, format!("`{field}` has shape {shape:?}; expected {want}")))
}

fn bad(path: &Path, message: String) -> DataError {
    DataError::Format { path: PathBuf::from(path), message }
}

impl FlatSteps {
    /// Checks every array (lengths, finite values, task ids in `0..num_tasks`, an episode end at
    /// the last step, one task per episode) and cuts the steps into one dataset per task present,
    /// by task index. `path` (the file the arrays came from) names every error.
    pub fn split_by_task(
        &self,
        path: &Path,
        num_tasks: usize,
    ) -> Result<BTreeMap<usize, TaskDataset>, DataError> {
        let n = self.rewards.len();
        if n == 0 {
            return Err(bad(path, "no steps (rewards is empty)".into()));
        }
        let lengths = [
            ("observations", self.observations.len(), n * self.obs_dim, "N x obs_dim"),
            ("actions", self.actions.len(), n * self.act_dim, "N x act_dim"),
            ("terminals", self.terminals.len(), n, "N"),
            ("timeouts", self.timeouts.len(), n, "N"),
            ("task_ids", self.task_ids.len(), n, "N"),
        ];
        for (field, got, want, shape) in lengths {
            if got != want {
                return Err(bad(
                    path,
                    format!("`{field}` has {got} values; {shape} is {want} (N = {n} rewards)"),
                ));
            }
        }
        let values = [
            ("observations", &self.observations, self.obs_dim),
            ("actions", &self.actions, self.act_dim),
            ("rewards", &self.rewards, 1),
        ];
        for (field, v, width) in values {
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(bad(
                    path,
                    format!("`{field}` at step {} is {}, not a finite number", i / width, v[i]),
                ));
            }
        }
        if let Some(i) = self.task_ids.iter().position(|&t| t < 0 || t as u64 >= num_tasks as u64) {
            return Err(bad(
                path,
                format!(
                    "`task_ids` at step {i} is {}; the suite has tasks 0..{num_tasks}",
                    self.task_ids[i]
                ),
            ));
        }
        if !(self.terminals[n - 1] || self.timeouts[n - 1]) {
            return Err(bad(
                path,
                format!(
                    "the last step ({}) ends no episode: set `terminals` or `timeouts` there \
                     (an episode cut in the middle cannot be trained on)",
                    n - 1
                ),
            ));
        }
        let mut tasks: BTreeMap<usize, Vec<Trajectory>> = BTreeMap::new();
        let mut start = 0;
        for end in (0..n).filter(|&i| self.terminals[i] || self.timeouts[i]) {
            let task = self.task_ids[start];
            if let Some(j) = (start..=end).find(|&j| self.task_ids[j] != task) {
                return Err(bad(
                    path,
                    format!(
                        "`task_ids` changes from {task} to {} at step {j}, inside the episode of \
                         steps {start}..={end}: an episode belongs to one task",
                        self.task_ids[j]
                    ),
                ));
            }
            let (od, ad) = (self.obs_dim, self.act_dim);
            let t = Trajectory::new(
                od,
                ad,
                self.observations[start * od..(end + 1) * od].to_vec(),
                self.actions[start * ad..(end + 1) * ad].to_vec(),
                self.rewards[start..=end].to_vec(),
                self.terminals[start..=end].to_vec(),
                // A step both terminal and timed out ended the MDP: one flag per end.
                (start..=end).map(|j| self.timeouts[j] && !self.terminals[j]).collect(),
            )
            .map_err(|e| e.in_file(path))?;
            tasks.entry(task as usize).or_default().push(t);
            start = end + 1;
        }
        let mut out = BTreeMap::new();
        for (task, trajs) in tasks {
            let ds = TaskDataset::new(trajs).map_err(|e| e.in_file(path))?;
            ds.check_values().map_err(|m| bad(path, format!("task {task}: {m}")))?;
            out.insert(task, ds);
        }
        Ok(out)
    }
}
