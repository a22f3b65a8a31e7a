//! Offline RL data for Prompt-DT: trajectories, per-task datasets, multi-task datasets.
//!
//! - [`Trajectory`]: one episode, with `terminated` (a true end of the MDP) and `truncated` (a time
//!   limit) kept apart. The reference release conflates them in one `terminals` array.
//! - [`TaskDataset`]: the trajectories of one task (a main dataset D_i or a prompt set P_i).
//! - [`MultiTaskDataset`]: D_i and P_i for every task, with task ids.
//! - [`mode`]: the datasets' vocabulary ([`mode::Mode`]: expert, medium, random; [`mode::Set`]).
//! - [`flat`]: flat step arrays with a task column cut into per-task datasets; prompt-set rules.
//! - [`native`]: the on-disk format (safetensors arrays + a JSON manifest), readable from Python.
//! - [`pickle`]: a reader for the reference release's `{env}-{task}-{mode}.pkl` files that never
//!   executes code.
//!
//! No tensor framework here: this crate is plain `Vec<f32>`, so its tests are fast.

pub mod error;
pub mod flat;
pub mod flat_hdf5;
pub mod inspect;
pub mod mode;
pub mod multitask;
pub mod native;
pub mod pickle;
pub mod reference;

pub use error::DataError;

use serde::{Deserialize, Serialize};

/// One episode. Arrays are row-major: `observations[t * obs_dim + j]`.
///
/// Invariants (checked by [`Trajectory::new`]): `observations.len() == T * obs_dim`,
/// `actions.len() == T * act_dim`, and `rewards`, `terminated`, `truncated` have length `T >= 1`.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// `[T, obs_dim]`: the observation *before* each action.
    pub observations: Vec<f32>,
    /// `[T, act_dim]`
    pub actions: Vec<f32>,
    /// `[T]`
    pub rewards: Vec<f32>,
    /// `[T]`: the episode ended here because the MDP terminated (e.g. Ant fell over).
    pub terminated: Vec<bool>,
    /// `[T]`: the episode was cut here by a time limit; the MDP itself did not end.
    pub truncated: Vec<bool>,
}

impl Trajectory {
    /// Builds a trajectory, checking that every array agrees on the length `T` and the dims.
    pub fn new(
        obs_dim: usize,
        act_dim: usize,
        observations: Vec<f32>,
        actions: Vec<f32>,
        rewards: Vec<f32>,
        terminated: Vec<bool>,
        truncated: Vec<bool>,
    ) -> Result<Self, DataError> {
        let t = rewards.len();
        let check = |field: &'static str, got: usize, want: usize| {
            if got == want {
                Ok(())
            } else {
                Err(DataError::Shape {
                    field,
                    expected: format!("{want} elements"),
                    got: format!("{got}"),
                })
            }
        };
        if t == 0 {
            return Err(DataError::Shape {
                field: "rewards",
                expected: "T >= 1".into(),
                got: "0".into(),
            });
        }
        if obs_dim == 0 || act_dim == 0 {
            return Err(DataError::Shape {
                field: "dims",
                expected: "obs_dim >= 1 and act_dim >= 1".into(),
                got: format!("obs_dim {obs_dim}, act_dim {act_dim}"),
            });
        }
        check("observations", observations.len(), t * obs_dim)?;
        check("actions", actions.len(), t * act_dim)?;
        check("terminated", terminated.len(), t)?;
        check("truncated", truncated.len(), t)?;
        Ok(Self { obs_dim, act_dim, observations, actions, rewards, terminated, truncated })
    }

    /// Number of steps `T`.
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    /// Always false: a trajectory has at least one step.
    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// Undiscounted return, summed in f64 (the reference sums float32 rewards with numpy).
    pub fn episode_return(&self) -> f64 {
        self.rewards.iter().map(|&r| r as f64).sum()
    }

    /// Observation at step `t`.
    pub fn obs(&self, t: usize) -> &[f32] {
        &self.observations[t * self.obs_dim..(t + 1) * self.obs_dim]
    }

    /// Action at step `t`.
    pub fn action(&self, t: usize) -> &[f32] {
        &self.actions[t * self.act_dim..(t + 1) * self.act_dim]
    }
}

/// Identifies a task: its environment family (`cheetah_vel`) and index within the family (`2`).
/// Its display form is the reference's task name, `cheetah_vel-2`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TaskId {
    pub env: String,
    pub index: usize,
}

impl std::fmt::Display for TaskId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}-{}", self.env, self.index)
    }
}

/// The trajectories of one task: a main offline dataset D_i or a few-shot prompt set P_i.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskDataset {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub trajectories: Vec<Trajectory>,
}

impl TaskDataset {
    /// Builds a dataset, checking that it is non-empty and that all trajectories share the dims.
    pub fn new(trajectories: Vec<Trajectory>) -> Result<Self, DataError> {
        let first = trajectories.first().ok_or(DataError::Empty)?;
        let (obs_dim, act_dim) = (first.obs_dim, first.act_dim);
        for (i, t) in trajectories.iter().enumerate() {
            if t.obs_dim != obs_dim || t.act_dim != act_dim {
                return Err(DataError::Shape {
                    field: "trajectories",
                    expected: format!("obs_dim {obs_dim}, act_dim {act_dim} in every trajectory"),
                    got: format!("trajectory {i}: obs_dim {}, act_dim {}", t.obs_dim, t.act_dim),
                });
            }
        }
        Ok(Self { obs_dim, act_dim, trajectories })
    }

    pub fn num_steps(&self) -> usize {
        self.trajectories.iter().map(Trajectory::len).sum()
    }

    pub fn returns(&self) -> Vec<f64> {
        self.trajectories.iter().map(Trajectory::episode_return).collect()
    }

    /// Checks that every value is finite and that every return-to-go fits an f32 with room to
    /// spare: a NaN, an infinity or a reward of 3e38 would otherwise train on NaN losses and
    /// surface only at the first evaluation. The message names the trajectory, field and step.
    pub fn check_values(&self) -> Result<(), String> {
        /// Returns-to-go are summed in f32 and then scaled; beyond this they lose all precision.
        const MAX_RETURN: f64 = 1e30;
        for (i, t) in self.trajectories.iter().enumerate() {
            let fields: [(&str, &[f32], usize); 3] = [
                ("observations", &t.observations, t.obs_dim),
                ("actions", &t.actions, t.act_dim),
                ("rewards", &t.rewards, 1),
            ];
            for (name, values, width) in fields {
                if let Some(k) = values.iter().position(|v| !v.is_finite()) {
                    return Err(format!(
                        "trajectory {i}: {name} at step {} is {} (every value must be finite)",
                        k / width,
                        values[k]
                    ));
                }
            }
            let mut rtg = 0.0f64;
            for (step, r) in t.rewards.iter().enumerate().rev() {
                rtg += f64::from(*r);
                if rtg.abs() > MAX_RETURN {
                    return Err(format!(
                        "trajectory {i}: the return-to-go from step {step} is {rtg:.3e}, beyond \
                         {MAX_RETURN:e} (rewards this large overflow the f32 return tokens)"
                    ));
                }
            }
        }
        Ok(())
    }
}

/// D_i and P_i for one task.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskData {
    pub id: TaskId,
    /// The main offline dataset D_i (history segments are drawn from it).
    pub dataset: TaskDataset,
    /// The few-shot demonstration set P_i (prompt segments are drawn from it).
    pub prompts: TaskDataset,
}

/// Several tasks of one environment family, all with the same dims.
#[derive(Debug, Clone, PartialEq)]
pub struct MultiTaskDataset {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub tasks: Vec<TaskData>,
}

impl MultiTaskDataset {
    /// Builds the set, checking that every D_i and P_i has the same dims.
    pub fn new(tasks: Vec<TaskData>) -> Result<Self, DataError> {
        let first = tasks.first().ok_or(DataError::Empty)?;
        let (obs_dim, act_dim) = (first.dataset.obs_dim, first.dataset.act_dim);
        for t in &tasks {
            for (which, d) in [("dataset", &t.dataset), ("prompts", &t.prompts)] {
                if d.obs_dim != obs_dim || d.act_dim != act_dim {
                    return Err(DataError::Shape {
                        field: "tasks",
                        expected: format!("obs_dim {obs_dim}, act_dim {act_dim} in every task"),
                        got: format!(
                            "{} {which}: obs_dim {}, act_dim {}",
                            t.id, d.obs_dim, d.act_dim
                        ),
                    });
                }
            }
        }
        Ok(Self { obs_dim, act_dim, tasks })
    }

    pub fn task(&self, id: &TaskId) -> Option<&TaskData> {
        self.tasks.iter().find(|t| &t.id == id)
    }

    /// A content hash of every value of every task (ids, D_i and P_i, in order), independent of
    /// the file format: `sha256:<hex>`. A run records it to refuse evaluating or resuming on data
    /// other than what it trained on.
    pub fn fingerprint(&self) -> String {
        use sha2::{Digest, Sha256};
        let mut h = Sha256::new();
        let floats = |h: &mut Sha256, v: &[f32]| {
            for x in v {
                h.update(x.to_le_bytes());
            }
        };
        for task in &self.tasks {
            h.update(task.id.env.as_bytes());
            h.update((task.id.index as u64).to_le_bytes());
            for set in [&task.dataset, &task.prompts] {
                h.update((set.trajectories.len() as u64).to_le_bytes());
                for t in &set.trajectories {
                    for n in [t.len(), t.obs_dim, t.act_dim] {
                        h.update((n as u64).to_le_bytes());
                    }
                    floats(&mut h, &t.observations);
                    floats(&mut h, &t.actions);
                    floats(&mut h, &t.rewards);
                    let flags: Vec<u8> = t
                        .terminated
                        .iter()
                        .zip(&t.truncated)
                        .map(|(&a, &b)| u8::from(a) | (u8::from(b) << 1))
                        .collect();
                    h.update(&flags);
                }
            }
        }
        let digest = h.finalize();
        let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
        format!("sha256:{hex}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rewards of 3e38 are finite, but their return-to-go is not representable: the message says
    /// so in one plain sentence (it once carried a run of stray spaces from a line continuation).
    #[test]
    fn an_overflowing_return_to_go_is_named_plainly() -> Result<(), DataError> {
        let rewards = vec![3e38f32, 3e38];
        let t = Trajectory::new(
            1,
            1,
            vec![0.0; 2],
            vec![0.0; 2],
            rewards,
            vec![false; 2],
            vec![false; 2],
        )?;
        let msg =
            TaskDataset::new(vec![t])?.check_values().expect_err("3e38 rewards must be refused");
        assert!(msg.contains("the return-to-go from step 1 is 3.000e38, beyond 1e30"), "{msg}");
        assert!(!msg.contains("  "), "stray spaces in: {msg:?}");
        Ok(())
    }
}
