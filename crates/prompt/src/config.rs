//! Sampling settings. Defaults reproduce the reference code; each place where the code and the paper
//! differ is an option with the paper's choice one value away.

use serde::{Deserialize, Serialize};

/// Where a prompt segment is cut from a demonstration trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PromptPosition {
    /// Reference code (`get_prompt`, pitfall 2): always the tail, steps `T-H-1 .. T-2`
    /// (`si = max(0, T - H - 1)`; the very last step is excluded).
    #[default]
    Tail,
    /// The paper's Algorithm 2: a uniformly random segment `si ~ U{0, .., T-H}` that lies wholly
    /// inside the trajectory (the whole trajectory, left-padded, if it is shorter than H).
    Random,
}

/// Which trajectories of a main dataset history segments are drawn from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrajectoryRanking {
    /// Reference code (`process_dataset`, pitfall 5): trajectories ranked by return, kept from the
    /// best while the kept steps stay *strictly* below the total, so the lowest-return trajectory
    /// of each task is never sampled (DT's off-by-one). Weights proportional to length.
    #[default]
    ReferenceOffByOne,
    /// The fix: every trajectory is kept. Weights proportional to length.
    All,
}

/// Which datasets the global state mean/std are computed over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NormalizationScope {
    /// Reference code (`--average_state_mean`, pitfall 4): the main datasets of the training tasks
    /// *and* the test tasks (a task in both lists counts twice).
    #[default]
    TrainAndTest,
    /// Training tasks' main datasets only (no test-task data leaks into training).
    TrainOnly,
    /// No normalisation (the reference's `--no_state_normalize`): mean 0, std 1.
    None,
}

/// Settings of prompt and history sampling.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SamplerConfig {
    /// History length K (20).
    pub k: usize,
    /// Prompt episodes J (`--prompt-episode`, 1).
    pub prompt_episodes: usize,
    /// Prompt segment length H (`--prompt-length`, 5). The prompt has J*H steps.
    pub prompt_length: usize,
    pub prompt_position: PromptPosition,
    /// Samples per training task in a batch, M (`--batch_size`; code 16, paper 8).
    pub batch_size_per_task: usize,
    /// Return-to-go divisor (`scale`; e.g. 500 for cheetah_vel).
    pub rtg_scale: f32,
    /// Timesteps are clipped to `max_ep_len - 1` (the environment's horizon, 200 for MuJoCo tasks).
    pub max_ep_len: usize,
    pub ranking: TrajectoryRanking,
    /// Prompt-MT-BC (`--no-rtg`): history returns-to-go are zeroed in training batches (the prompt's
    /// are kept, as in the reference).
    pub zero_history_returns: bool,
}

impl SamplerConfig {
    /// The reference code's defaults for a given return scale and horizon.
    pub fn reference(rtg_scale: f32, max_ep_len: usize) -> Self {
        Self {
            k: 20,
            prompt_episodes: 1,
            prompt_length: 5,
            prompt_position: PromptPosition::Tail,
            batch_size_per_task: 16,
            rtg_scale,
            max_ep_len,
            ranking: TrajectoryRanking::ReferenceOffByOne,
            zero_history_returns: false,
        }
    }

    /// Prompt steps J*H.
    pub fn prompt_steps(&self) -> usize {
        self.prompt_episodes * self.prompt_length
    }

    /// Checks the settings, given the model's token limit (`n_positions`, 1024).
    pub fn validate(&self, n_positions: usize) -> Result<(), SamplerError> {
        let bad = |field: &'static str, why: String| Err(SamplerError::Config { field, why });
        for (field, v) in [
            ("k", self.k),
            ("prompt_episodes", self.prompt_episodes),
            ("prompt_length", self.prompt_length),
            ("batch_size_per_task", self.batch_size_per_task),
            ("max_ep_len", self.max_ep_len),
        ] {
            if v == 0 {
                return bad(field, "must be at least 1".into());
            }
        }
        if !(self.rtg_scale.is_finite() && self.rtg_scale > 0.0) {
            return bad("rtg_scale", format!("must be a positive number, got {}", self.rtg_scale));
        }
        let tokens = 3 * (self.prompt_steps() + self.k);
        if tokens > n_positions {
            return bad(
                "k",
                format!(
                    "3 x (J*H + K) = 3 x ({} + {}) = {tokens} tokens exceeds the model's n_positions = {n_positions}",
                    self.prompt_steps(),
                    self.k
                ),
            );
        }
        Ok(())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SamplerError {
    #[error("sampler setting `{field}` {why}")]
    Config { field: &'static str, why: String },
    #[error("task {task}: {why}")]
    Task { task: String, why: String },
}
