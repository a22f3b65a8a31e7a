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

/// `--adapt KIND`: one family for every test-time adaptation, `--adapt-steps` and `--adapt-batch`
/// its budget whichever it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdaptArg {
    /// One of `[eval.adapt]`'s: soft-prompt, ptdt, lora, the backbone frozen, full (or none).
    Prompt(pdt_rundir::config::AdaptKind),
    /// MACAW's gradient steps on each task's transitions (a MACAW run's own adaptation).
    Macaw,
    /// MT-BC-Finetune's fine-tuning on each test task's demonstrations (its run's own).
    Finetune,
}

impl AdaptArg {
    /// The `[eval.adapt]` kind, for the adaptations that have one.
    pub(crate) fn prompt_kind(self) -> Option<pdt_rundir::config::AdaptKind> {
        match self {
            AdaptArg::Prompt(k) => Some(k),
            AdaptArg::Macaw | AdaptArg::Finetune => None,
        }
    }

    pub(crate) fn name(self) -> &'static str {
        match self {
            AdaptArg::Prompt(k) => k.name(),
            AdaptArg::Macaw => "macaw",
            AdaptArg::Finetune => "finetune",
        }
    }
}

/// An adaptation by name (`--adapt`); the error names the value and the known names.
fn adapt_kind(s: &str) -> Result<AdaptArg, String> {
    match s {
        "macaw" => Ok(AdaptArg::Macaw),
        "finetune" => Ok(AdaptArg::Finetune),
        _ => s.parse().map(AdaptArg::Prompt).map_err(|e: pdt_rundir::config::AdaptError| {
            format!("{e}, or a method's own: macaw, finetune")
        }),
    }
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
    /// Test-time adaptation to each test task from its demonstrations (docs/prompt-control.md):
    /// soft-prompt, ptdt, lora (the backbone frozen), full (every weight fine-tuned at their
    /// budget; eval only, the weights restored after each task); eval also takes a run's own, macaw (MACAW's
    /// gradient steps) or finetune (MT-BC-Finetune's fine-tuning). --adapt-steps and
    /// --adapt-batch set its budget: iterations and demonstration segments (macaw:
    /// transitions) per iteration. eval: default the run's own ([eval.adapt], none unless set),
    /// results of soft-prompt, ptdt, lora and full to eval_adapt_<kind>.json; serve: episodes opened
    /// with a `task` (default none; a request's `adapt` names one).
    #[arg(long, value_parser = adapt_kind)]
    pub adapt: Option<AdaptArg>,
    /// --adapt soft-prompt / lora / full: Adam's learning rate.
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

impl AdaptFlags {
    /// Sets the adaptation settings these flags name (and the budget's `steps` and `batch`) in
    /// `c`; the kind is the caller's. Values are checked by `AdaptConfig::validate`.
    pub(crate) fn apply(
        &self,
        c: &mut pdt_rundir::config::AdaptConfig,
        steps: Option<usize>,
        batch: Option<usize>,
    ) {
        c.steps = steps.unwrap_or(c.steps);
        c.batch = batch.unwrap_or(c.batch);
        c.lr = self.adapt_lr.unwrap_or(c.lr);
        c.ptdt.candidates = self.ptdt_candidates.unwrap_or(c.ptdt.candidates);
        c.ptdt.sigma = self.ptdt_sigma.unwrap_or(c.ptdt.sigma);
        c.ptdt.step = self.ptdt_step.unwrap_or(c.ptdt.step);
        c.ptdt.score = self.ptdt_score.unwrap_or(c.ptdt.score);
        c.lora.rank = self.lora_rank.unwrap_or(c.lora.rank);
        c.lora.alpha = self.lora_alpha.unwrap_or(c.lora.alpha);
        c.lora.c_proj |= self.lora_c_proj;
    }
}

/// `promptdt serve`'s adaptation flags: the evaluation's, and the budget (`promptdt eval` shares
/// `--adapt-steps` / `--adapt-batch` with MACAW's adaptation).
#[derive(Debug, clap::Args)]
pub struct ServeAdaptFlags {
    #[command(flatten)]
    pub flags: AdaptFlags,
    /// Adaptation iterations per task (gradient steps; ptdt: ranking updates; default 20).
    #[arg(long)]
    pub adapt_steps: Option<usize>,
    /// Demonstration segments per adaptation iteration (default 16).
    #[arg(long)]
    pub adapt_batch: Option<usize>,
}

impl ServeAdaptFlags {
    /// The server's adaptation: the kind `--adapt` names (none without it; a request's `adapt`
    /// names one) and the budget these flags set. A method's own adaptation is refused: the
    /// methods that adapt before acting are not served.
    pub(crate) fn to_config(&self) -> Result<pdt_rundir::config::AdaptConfig, String> {
        let kind = match self.flags.adapt {
            None => Default::default(),
            Some(a) => a.prompt_kind().ok_or_else(|| {
                format!(
                    "--adapt {}: a method's own adaptation is evaluated (`promptdt eval`), not \
                     served; serve adapts with soft-prompt, ptdt or lora",
                    a.name()
                )
            })?,
        };
        let mut c = pdt_rundir::config::AdaptConfig { kind, ..Default::default() };
        self.flags.apply(&mut c, self.adapt_steps, self.adapt_batch);
        Ok(c)
    }
}
