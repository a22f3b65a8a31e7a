//! `promptdt eval`'s test-time flags into the evaluation's request: the prompt strategy and the
//! adaptation they ask for on top of the run's own, and the flags that act only with another.

/// The `[eval.adapt]` adaptation `promptdt eval`'s flags ask for, on top of the run's; `None`
/// without `--adapt` or with a method's own. Values are checked by the evaluation
/// (`AdaptConfig::validate`).
pub(crate) fn eval_adapt(
    a: &crate::args::EvalArgs,
    run: &pdt_rundir::config::AdaptConfig,
) -> Option<pdt_rundir::config::AdaptConfig> {
    let kind = a.adaptation.adapt?.prompt_kind()?;
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
        ("--bandit-epsilon-decay", a.bandit_epsilon_decay.is_some()),
        ("--bandit-explore-fraction", a.bandit_explore_fraction.is_some()),
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
    let kind = f.adapt.and_then(crate::prompt_args::AdaptArg::prompt_kind);
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

/// The budget of the run's own adaptation (MACAW's, MT-BC-Finetune's) the flags ask for, checked
/// against the run's test time: `--adapt macaw` / `--adapt finetune` with the run that has it,
/// or (the older form, with a note on stderr) `--adapt-steps` / `--adapt-batch` without
/// `--adapt`. `None`: the flags ask for none (the run's own budget, or an `[eval.adapt]` kind).
pub(crate) fn own_budget(
    a: &crate::args::EvalArgs,
    test_time: &pdt_rundir::config::TestTime,
    method: pdt_rundir::config::Method,
) -> Result<Option<pdt_train::run::MacawAdaptation>, String> {
    use crate::prompt_args::AdaptArg;
    use pdt_rundir::config::Adaptation;
    let budget = pdt_train::run::MacawAdaptation { steps: a.adapt_steps, batch: a.adapt_batch };
    let own = match test_time.adaptation() {
        Some(Adaptation::Macaw { .. }) => Some(AdaptArg::Macaw),
        Some(Adaptation::Finetune { .. }) => Some(AdaptArg::Finetune),
        Some(Adaptation::Prompt(_)) | None => None,
    };
    match a.adaptation.adapt {
        Some(AdaptArg::Prompt(_)) => Ok(None),
        Some(asked @ (AdaptArg::Macaw | AdaptArg::Finetune)) if Some(asked) != own => Err(format!(
            "--adapt {}: this run is {}, whose own adaptation is {}",
            asked.name(),
            method.name(),
            own.map_or("none", AdaptArg::name)
        )),
        Some(_) => Ok(Some(budget)),
        None if budget == pdt_train::run::MacawAdaptation::default() => Ok(None),
        None => {
            // The older spelling: the budget without the kind meant MACAW's. Still read, so
            // scripts keep working; the evaluation refuses it for a run without its own.
            if let Some(own) = own {
                eprintln!(
                    "note: --adapt-steps / --adapt-batch without --adapt set the run's own \
                     adaptation; write --adapt {} --adapt-steps N",
                    own.name()
                );
            }
            Ok(Some(budget))
        }
    }
}

/// The prompt strategy the flags ask for; `None` when no prompt flag is given (the run's own).
pub(crate) fn eval_prompt(a: &crate::args::EvalArgs) -> Option<pdt_prompt::PromptStrategy> {
    let any = a.prompt_strategy.is_some()
        || a.prompt_episodes.is_some()
        || a.prompt_length.is_some()
        || a.prompt_stride.is_some()
        || a.bandit_rule.is_some()
        || a.bandit_epsilon.is_some()
        || a.bandit_epsilon_decay.is_some()
        || a.bandit_explore_fraction.is_some()
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
            epsilon_decay: a.bandit_epsilon_decay.unwrap_or(d.epsilon_decay),
            explore_fraction: a.bandit_explore_fraction,
            episodes_per_round: a.bandit_round.unwrap_or(d.episodes_per_round),
            ..d
        },
    })
}
