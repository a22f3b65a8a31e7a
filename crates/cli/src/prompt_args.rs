//! The parsers of the test-time prompt flags of `promptdt eval` and `promptdt serve`
//! (docs/prompt-control.md) into `pdt_prompt`'s types, the one owner of prompt strategies, and of
//! `promptdt eval`'s adaptation flags into `pdt_rundir::config`'s (`[eval.adapt]`).

/// A prompt strategy by name; the error names the value and the known names.
pub(crate) fn prompt_strategy(s: &str) -> Result<pdt_prompt::PromptStrategyKind, String> {
    s.parse().map_err(|e: pdt_prompt::StrategyError| e.to_string())
}

pub(crate) fn bandit_rule(s: &str) -> Result<pdt_prompt::BanditRule, String> {
    match s {
        "epsilon-greedy" => Ok(pdt_prompt::BanditRule::EpsilonGreedy),
        "ucb" => Ok(pdt_prompt::BanditRule::Ucb),
        other => Err(format!("unknown bandit rule `{other}` (known: epsilon-greedy, ucb)")),
    }
}

/// An evaluation-time adaptation by name (`--adapt`); the error names the value and the known names.
fn adapt_kind(s: &str) -> Result<pdt_rundir::config::AdaptKind, String> {
    s.parse().map_err(|e: pdt_rundir::config::AdaptError| e.to_string())
}

fn ptdt_score(s: &str) -> Result<pdt_rundir::config::PtdtScore, String> {
    match s {
        "action-loss" => Ok(pdt_rundir::config::PtdtScore::ActionLoss),
        "return" => Ok(pdt_rundir::config::PtdtScore::Return),
        other => Err(format!("unknown ptdt score `{other}` (known: action-loss, return)")),
    }
}

/// `promptdt eval`'s evaluation-time adaptation flags (flattened into its arguments).
#[derive(Debug, clap::Args)]
pub struct AdaptFlags {
    /// Evaluation-time adaptation to each test task from its demonstrations, the backbone
    /// frozen (docs/prompt-control.md): soft-prompt, ptdt, lora (default: the run's
    /// [eval.adapt], none unless set). Results go to eval_adapt_<kind>.json. With it,
    /// --adapt-steps and --adapt-batch set the adaptation's iterations and demonstration
    /// segments per iteration.
    #[arg(long, value_parser = adapt_kind)]
    pub adapt: Option<pdt_rundir::config::AdaptKind>,
    /// --adapt soft-prompt / lora: Adam's learning rate.
    #[arg(long)]
    pub adapt_lr: Option<f64>,
    /// --adapt ptdt: candidates per iteration.
    #[arg(long)]
    pub ptdt_candidates: Option<usize>,
    /// --adapt ptdt: standard deviation of the perturbations.
    #[arg(long)]
    pub ptdt_sigma: Option<f64>,
    /// --adapt ptdt: step along the ranking direction.
    #[arg(long)]
    pub ptdt_step: Option<f64>,
    /// --adapt ptdt: what ranks the candidates: action-loss (default, offline) or return.
    #[arg(long, value_parser = ptdt_score)]
    pub ptdt_score: Option<pdt_rundir::config::PtdtScore>,
    /// --adapt lora: rank r.
    #[arg(long)]
    pub lora_rank: Option<usize>,
    /// --adapt lora: alpha (the delta is scaled by alpha / r).
    #[arg(long)]
    pub lora_alpha: Option<f64>,
    /// --adapt lora: also adapt attn.c_proj.
    #[arg(long)]
    pub lora_c_proj: bool,
}
