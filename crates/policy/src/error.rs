use std::path::PathBuf;

/// Why a run cannot be loaded as a policy, or why an input to it is refused.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error(transparent)]
    Config(#[from] pdt_rundir::config::ConfigError),
    #[error(transparent)]
    Env(#[from] pdt_envs::EnvError),
    #[error(transparent)]
    Sampler(#[from] pdt_prompt::SamplerError),
    #[error(transparent)]
    Strategy(#[from] pdt_prompt::StrategyError),
    #[error(transparent)]
    Eval(#[from] pdt_eval::EvalError),
    #[error(transparent)]
    Checkpoint(#[from] pdt_model::checkpoint::CheckpointError),
    #[error(transparent)]
    Device(#[from] pdt_torch::device::DeviceError),
    #[error(transparent)]
    RunDir(#[from] pdt_rundir::RunDirError),
    /// The run's configuration, data or files (`pdt_run`: not a run directory, no checkpoint
    /// yet, a corrupt `task_stats.json`, data that do not fit the configuration).
    #[error(transparent)]
    Load(#[from] pdt_run::LoadError),
    /// A run of a method without the Decision Transformer (MACAW): it has no policy here.
    #[error(
        "{}: a {method} run adapts to a task's data before it acts and has no Decision \
         Transformer policy to serve or film (evaluate it with `promptdt eval`)",
        dir.display()
    )]
    NotTransformer { dir: PathBuf, method: &'static str },
    /// A run whose evaluation adapts its weights to each test task before acting
    /// (MT-BC-Finetune): its checkpoint as saved is not the policy its evaluation scores
    /// ([`crate::Policy::check_acts_as_evaluated`]).
    #[error(
        "an {method} run adapts to each test task before it acts (its evaluation fine-tunes the \
         multi-task weights on the task's demonstrations first), so its checkpoint as saved is \
         not the policy it is evaluated as: `promptdt {command}` takes {acting} runs (evaluate this \
         one with `promptdt eval`)"
    )]
    AdaptsBeforeActing { method: &'static str, command: &'static str, acting: String },
    /// The run's configuration and data do not fit together (the trainer's checks).
    #[error("{0}")]
    Invalid(String),
    /// An input refused: an observation, reward, target return or prompt, named in the message.
    #[error("{0}")]
    Input(String),
    #[error("task {task} is not one of the run's tasks ({known})")]
    UnknownTask { task: usize, known: String },
    /// Task prompts or plans asked for, but the run's data could not be read (or changed).
    #[error("{what}{why}")]
    Unavailable { what: &'static str, why: String },
    /// The episode has as many steps as the model has timesteps.
    #[error("the episode has reached the model's max_ep_len ({max_ep_len} steps)")]
    EpisodeFull { max_ep_len: usize },
    #[error(
        "the policy's action is not finite ({action:?}): {inputs}; values this far from the \
         run's data overflow the model's f32 arithmetic"
    )]
    ActionNotFinite { action: Vec<f32>, inputs: String },
}
