//! `promptdt eval`'s test-time flags into the evaluation's request: the prompt strategy and the
//! adaptation they ask for on top of the run's own, and the flags that act only with another.

/// The adaptation `promptdt eval`'s flags ask for, on top of the run's `[eval.adapt]`; `None`
/// without `--adapt`. Values are checked by the evaluation (`AdaptConfig::validate`).
pub(crate) fn eval_adapt(
    a: &crate::args::EvalArgs,
    run: &pdt_rundir::config::AdaptConfig,
) -> Option<pdt_rundir::config::AdaptConfig> {
    let kind = a.adaptation.adapt?;
    let mut c = run.clone();
    c.kind = kind;
    a.adaptation.apply(&mut c, a.adapt_steps, a.adapt_batch);
    Some(c)
}

/// `promptdt eval`'s flags that act only together with another: refused by name, not ignored (an
/// ignored `--bandit-epsilon` was even recorded in the evaluation's file as if it had acted). A
/// prompt flag given alone replaces the run's strategy by `reference` (`commands::eval_prompt`),
/// and without `--adapt` the run's own `[eval.adapt]` applies, so each needs its flag here.
pub(crate) fn check_eval_flags(a: &crate::args::EvalArgs) -> Result<(), String> {
    use pdt_prompt::PromptStrategyKind as S;
    use pdt_rundir::config::AdaptKind as K;
    let strategy = a.prompt_strategy.unwrap_or_default();
    let bandit = [
        ("--bandit-rule", a.bandit_rule.is_some()),
        ("--bandit-epsilon", a.bandit_epsilon.is_some()),
        ("--bandit-round", a.bandit_round.is_some()),
    ];
    for (flag, given) in bandit {
        if given && strategy != S::Bandit {
            return Err(format!("{flag} acts only with --prompt-strategy bandit"));
        }
    }
    if a.prompt_stride.is_some() && !matches!(strategy, S::NearestStart | S::Bandit) {
        return Err(
            "--prompt-stride acts only with --prompt-strategy nearest-start or bandit".into()
        );
    }
    let f = &a.adaptation;
    let kind = f.adapt;
    let adapt = [
        ("--adapt-lr", f.adapt_lr.is_some(), &[K::SoftPrompt, K::Lora][..], "soft-prompt or lora"),
        ("--ptdt-candidates", f.ptdt_candidates.is_some(), &[K::Ptdt][..], "ptdt"),
        ("--ptdt-sigma", f.ptdt_sigma.is_some(), &[K::Ptdt][..], "ptdt"),
        ("--ptdt-step", f.ptdt_step.is_some(), &[K::Ptdt][..], "ptdt"),
        ("--ptdt-score", f.ptdt_score.is_some(), &[K::Ptdt][..], "ptdt"),
        ("--lora-rank", f.lora_rank.is_some(), &[K::Lora][..], "lora"),
        ("--lora-alpha", f.lora_alpha.is_some(), &[K::Lora][..], "lora"),
        ("--lora-c-proj", f.lora_c_proj, &[K::Lora][..], "lora"),
    ];
    for (flag, given, kinds, names) in adapt {
        if given && !kind.is_some_and(|k| kinds.contains(&k)) {
            return Err(format!("{flag} acts only with --adapt {names}"));
        }
    }
    Ok(())
}

/// The prompt strategy the flags ask for; `None` when no prompt flag is given (the run's own).
pub(crate) fn eval_prompt(a: &crate::args::EvalArgs) -> Option<pdt_prompt::PromptStrategy> {
    let any = a.prompt_strategy.is_some()
        || a.prompt_episodes.is_some()
        || a.prompt_length.is_some()
        || a.prompt_stride.is_some()
        || a.bandit_rule.is_some()
        || a.bandit_epsilon.is_some()
        || a.bandit_round.is_some();
    if !any {
        return None;
    }
    let d = pdt_prompt::BanditConfig::default();
    Some(pdt_prompt::PromptStrategy {
        strategy: a.prompt_strategy.unwrap_or_default(),
        episodes: a.prompt_episodes,
        length: a.prompt_length,
        stride: a.prompt_stride,
        bandit: pdt_prompt::BanditConfig {
            rule: a.bandit_rule.unwrap_or(d.rule),
            epsilon: a.bandit_epsilon.unwrap_or(d.epsilon),
            episodes_per_round: a.bandit_round.unwrap_or(d.episodes_per_round),
            ..d
        },
    })
}
