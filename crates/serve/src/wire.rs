//! The wire format of `promptdt serve` (docs/serve.md): the JSON bodies of its requests and
//! replies.

use serde::{Deserialize, Serialize};

// A prompt sent by the client is the arrays a Python `Policy` takes: one type, the policy's.
use pdt_policy::PromptArrays;

/// `POST /v1/episodes`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpenRequest {
    /// The prompt as arrays; or
    #[serde(default)]
    pub prompt: Option<PromptArrays>,
    /// a task of the run, whose prompt the server draws as the evaluation does
    #[serde(default)]
    pub task: Option<usize>,
    /// with this seed (default 0).
    #[serde(default)]
    pub prompt_seed: Option<u64>,
    /// How a `task`'s prompt is chosen (`docs/prompt-control.md`): `reference` (the evaluation's
    /// draw), `random-segment`, `best-return`, `nearest-start` (nearest this episode's first
    /// observation) or `bandit` (one per task on the server, learning from the returns of the
    /// task's closed episodes). Default: the server's `--prompt-strategy`.
    #[serde(default)]
    pub prompt_strategy: Option<String>,
    /// Test-time prompt segments J and steps per segment H (default: the server's, else the
    /// run's).
    #[serde(default)]
    pub prompt_episodes: Option<usize>,
    #[serde(default)]
    pub prompt_length: Option<usize>,
    /// Adapt to the `task` from its demonstrations before acting (`soft-prompt`, `ptdt`, `lora`,
    /// or `none`), with the server's `--adapt-*` budget, starting from the prompt the strategy
    /// picks (`reference`, `random-segment` or `best-return`). The first episode of a task, seed
    /// and settings waits for the adaptation; the server keeps it for the next ones. Default: the
    /// server's `--adapt`.
    #[serde(default)]
    pub adapt: Option<String>,
    /// G* (default: the run's).
    #[serde(default)]
    pub target_return: Option<f64>,
    /// The first observation (raw).
    pub observation: Vec<f64>,
}

/// `POST /v1/episodes/{id}/step`: the reward of the last action and the observation after it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepRequest {
    pub reward: f64,
    pub observation: Vec<f64>,
}

/// The action to take at step `t` of episode `episode`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionReply {
    pub episode: u64,
    pub t: usize,
    pub action: Vec<f32>,
    /// The opening reply of an episode whose prompt a strategy other than `reference` chose:
    /// the segments it is made of (demonstration, first step), in prompt order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prompt_segments: Option<Vec<pdt_prompt::SegmentChoice>>,
    /// The opening reply of an adapted episode: its task's adaptation (the demonstrations' probe
    /// loss before and after, values adapted, seconds it took when it was made).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptation: Option<pdt_rundir::config::AdaptLog>,
}

/// `GET /v1/info`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Info {
    pub method: String,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub k: usize,
    pub prompt_steps: usize,
    pub uses_prompt: bool,
    pub target_return: f32,
    pub rtg_scale: f32,
    pub max_ep_len: usize,
    pub iteration: u64,
    /// Tasks `task` may name (empty when the run's data were not readable).
    pub prompt_tasks: Vec<usize>,
    pub max_episodes: usize,
    pub max_batch: usize,
    pub open_episodes: usize,
}
