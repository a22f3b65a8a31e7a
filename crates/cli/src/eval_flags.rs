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
        (
            "--adapt-lr",
            f.adapt_lr.is_some(),
            &[K::SoftPrompt, K::Lora, K::Full][..],
            "soft-prompt, lora or full",
        ),
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

/// The test time `promptdt eval`'s flags ask for: the run's own ([`TestTime::of`] its
/// configuration) with the prompt strategy, the `[eval.adapt]` adaptation or the budget of the
/// run's own adaptation the flags change; `None` when no flag changes it. Reads the run's
/// configuration only then.
///
/// [`TestTime::of`]: pdt_rundir::config::TestTime::of
pub(crate) fn eval_test_time(
    a: &crate::args::EvalArgs,
) -> anyhow::Result<Option<pdt_rundir::config::TestTime>> {
    use pdt_rundir::config::TestTime;
    let prompt = eval_prompt(a);
    let budget = a.adapt_steps.is_some() || a.adapt_batch.is_some();
    if prompt.is_none() && a.adaptation.adapt.is_none() && !budget {
        return Ok(None);
    }
    let run = pdt_rundir::RunDir::at(&a.run);
    let cfg = pdt_run::files::run_config(&run, None, a.data.as_deref())?;
    let adapt = eval_adapt(a, &cfg.eval.adapt);
    let mut test_time = TestTime::with_settings(&cfg, prompt.as_ref(), adapt.as_ref());
    if own_budget(a, &TestTime::of(&cfg), cfg.run.method).map_err(anyhow::Error::msg)? {
        if let TestTime::Adapt { adaptation, .. } = &mut test_time {
            *adaptation = adaptation.with_budget(a.adapt_steps, a.adapt_batch);
        }
    }
    Ok(Some(test_time))
}

/// Whether the flags change the budget of the run's own adaptation (MACAW's, MT-BC-Finetune's),
/// checked against the run's test time: `--adapt macaw` / `--adapt finetune` with the run that
/// has it, or (the older form, with a note on stderr) `--adapt-steps` / `--adapt-batch` without
/// `--adapt`. `false`: they ask for none (the run's own budget, or an `[eval.adapt]` kind's).
fn own_budget(
    a: &crate::args::EvalArgs,
    test_time: &pdt_rundir::config::TestTime,
    method: pdt_rundir::config::Method,
) -> Result<bool, String> {
    use crate::prompt_args::AdaptArg;
    use pdt_rundir::config::Adaptation;
    let budget = a.adapt_steps.is_some() || a.adapt_batch.is_some();
    let own = match test_time.adaptation() {
        Some(Adaptation::Macaw { .. }) => Some(AdaptArg::Macaw),
        Some(Adaptation::Finetune { .. }) => Some(AdaptArg::Finetune),
        Some(Adaptation::Prompt(_)) | None => None,
    };
    match (a.adaptation.adapt, own) {
        (Some(AdaptArg::Prompt(_)), _) => Ok(false),
        (Some(asked @ (AdaptArg::Macaw | AdaptArg::Finetune)), _) if Some(asked) != own => {
            Err(format!(
                "--adapt {}: this run is {}, whose own adaptation is {}",
                asked.name(),
                method.name(),
                own.map_or("none", AdaptArg::name)
            ))
        }
        (Some(_), _) => Ok(budget),
        (None, _) if !budget => Ok(false),
        (None, Some(own)) => {
            // The older spelling: the budget without the kind meant MACAW's. Still read, so
            // scripts keep working.
            eprintln!(
                "note: --adapt-steps / --adapt-batch without --adapt set the run's own \
                 adaptation; write --adapt {} --adapt-steps N",
                own.name()
            );
            Ok(true)
        }
        (None, None) => Err(format!(
            "{}: --adapt-steps / --adapt-batch without --adapt change a MACAW or MT-BC-Finetune \
             run's own adaptation; this run is {} (name an adaptation: --adapt KIND)",
            a.run.display(),
            method.name()
        )),
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
