//! [`TestTime`]: what an evaluation does besides acting with the trained weights, as one value:
//! the reference rule, another prompt strategy, or an adaptation to each test task (`[eval.adapt]`'s
//! soft prompt, PTDT and LoRA, MT-BC-Finetune's fine-tuning, MACAW's gradient steps). A learner's
//! evaluation takes it (`pdt_train`'s `Learner::evaluate`), so no learner decides by its method
//! or its configuration which of them runs.

use super::{AdaptConfig, AdaptKind, ConfigError, Method, TrainConfig};
use pdt_prompt::PromptStrategy;

/// What an evaluation does at test time.
#[derive(Debug, Clone, PartialEq)]
pub enum TestTime {
    /// Each task's prompt as the reference draws it, the weights as trained.
    Reference,
    /// A prompt strategy other than the reference rule (`[eval.prompt]`).
    Strategy(PromptStrategy),
    /// An adaptation to each test task before its episodes, starting from `from`'s prompt (the
    /// methods with a prompt); training tasks are evaluated with `from` alone, except by MACAW,
    /// whose policy is its adaptation.
    Adapt { from: PromptStrategy, adaptation: Adaptation },
}

/// An adaptation to a task's demonstrations, and whose it is.
#[derive(Debug, Clone, PartialEq)]
pub enum Adaptation {
    /// `[eval.adapt]`: soft prompt, PTDT or LoRA, the backbone frozen (the methods with a prompt).
    Prompt(AdaptConfig),
    /// MT-BC-Finetune: a copy of every weight fine-tuned on the task's data
    /// (`eval.finetune_steps` steps of `eval.finetune_batch` segments at `eval.finetune_lr`, of
    /// `eval.finetune_data`).
    Finetune { steps: u64, batch: usize, lr: f64, data: super::FinetuneData },
    /// MACAW: its value function and policy adapted with `steps` gradient steps on `batch`
    /// transitions of the task (`[macaw]`'s `adapt_steps`, `adapt_batch`).
    Macaw { steps: usize, batch: usize },
}

impl TestTime {
    /// The run's own: its method's adaptation (fine-tuning, MACAW), else `[eval.adapt]`'s, else
    /// `[eval.prompt]`'s strategy, else the reference rule.
    pub fn of(cfg: &TrainConfig) -> Self {
        let e = &cfg.eval;
        let adaptation = match cfg.run.method {
            Method::MtBcFinetune => Some(Adaptation::Finetune {
                steps: e.finetune_steps,
                batch: e.finetune_batch,
                lr: e.finetune_lr,
                data: e.finetune_data,
            }),
            Method::Macaw => Some(Adaptation::Macaw {
                steps: cfg.macaw.adapt_steps,
                batch: cfg.macaw.adapt_batch,
            }),
            Method::PromptDt | Method::PromptMtBc | Method::MtOrl => {
                (!e.adapt.is_none()).then(|| Adaptation::Prompt(e.adapt.clone()))
            }
        };
        match adaptation {
            Some(adaptation) => TestTime::Adapt { from: e.prompt.clone(), adaptation },
            None if e.prompt.is_default() => TestTime::Reference,
            None => TestTime::Strategy(e.prompt.clone()),
        }
    }

    /// The run's own test time with `[eval.prompt]` and `[eval.adapt]` replaced where given: what
    /// an evaluation's request (`promptdt eval --prompt-strategy` / `--adapt`, Python's
    /// `evaluate`) asks of the run of `cfg`.
    pub fn with_settings(
        cfg: &TrainConfig,
        prompt: Option<&PromptStrategy>,
        adapt: Option<&AdaptConfig>,
    ) -> Self {
        let mut changed = cfg.clone();
        if let Some(p) = prompt {
            changed.eval.prompt = p.clone();
        }
        match adapt {
            // Asked for by name, so never hidden by the method's own (which `of` puts first):
            // `apply_to` refuses it for a method without a prompt.
            Some(a) if !a.is_none() => {
                let from = changed.eval.prompt;
                TestTime::Adapt { from, adaptation: Adaptation::Prompt(a.clone()) }
            }
            Some(a) => {
                changed.eval.adapt = a.clone();
                Self::of(&changed)
            }
            None => Self::of(&changed),
        }
    }

    /// Writes this test time into `cfg` as the run's own, so that `cfg.validate()` checks its
    /// settings as a run's (ranges, a strategy for a method without a prompt) and
    /// [`TestTime::of`] gives it back. A test time the run's method cannot have is refused by
    /// name: another method's adaptation (MACAW's for a Prompt-DT run), or none for a method whose
    /// policy is its adaptation (MACAW) or that adapts before it acts (MT-BC-Finetune).
    pub fn apply_to(&self, cfg: &mut TrainConfig) -> Result<(), ConfigError> {
        let e = &mut cfg.eval;
        match self {
            TestTime::Reference => {
                e.prompt = PromptStrategy::default();
                e.adapt.kind = AdaptKind::None;
            }
            TestTime::Strategy(s) => {
                e.prompt = s.clone();
                e.adapt.kind = AdaptKind::None;
            }
            TestTime::Adapt { from, adaptation } => {
                e.prompt = from.clone();
                match adaptation {
                    Adaptation::Prompt(a) => e.adapt = a.clone(),
                    &Adaptation::Finetune { steps, batch, lr, data } => {
                        e.adapt.kind = AdaptKind::None;
                        (e.finetune_steps, e.finetune_batch, e.finetune_lr) = (steps, batch, lr);
                        e.finetune_data = data;
                    }
                    &Adaptation::Macaw { steps, batch } => {
                        e.adapt.kind = AdaptKind::None;
                        (cfg.macaw.adapt_steps, cfg.macaw.adapt_batch) = (steps, batch);
                    }
                }
            }
        }
        let own = Self::of(cfg);
        if own == self.normalised() {
            return Ok(());
        }
        let method = cfg.run.method;
        if let (Some(Adaptation::Prompt(a)), false) = (self.adaptation(), method.uses_prompt()) {
            return Err(ConfigError::Invalid(format!(
                "eval.adapt.kind = {}: {} takes no prompt; the adaptations apply to {} runs",
                a.kind,
                method.name(),
                Method::names_where(Method::uses_prompt)
            )));
        }
        Err(ConfigError::Invalid(format!(
            "a {} run evaluates with {}, not {}",
            cfg.run.method.name(),
            own.adaptation().map_or("no adaptation of its own", Adaptation::name),
            self.adaptation().map_or("no adaptation", Adaptation::name)
        )))
    }

    /// The same test time with the reference rule written as [`TestTime::Reference`], as
    /// [`TestTime::of`] writes it.
    fn normalised(&self) -> Self {
        match self {
            TestTime::Strategy(s) if s.is_default() => TestTime::Reference,
            other => other.clone(),
        }
    }

    /// The adaptation, if any.
    pub fn adaptation(&self) -> Option<&Adaptation> {
        match self {
            TestTime::Adapt { adaptation, .. } => Some(adaptation),
            TestTime::Reference | TestTime::Strategy(_) => None,
        }
    }

    /// The prompt strategy its episodes start from (the reference rule's for [`TestTime::Reference`]).
    pub fn strategy(&self) -> PromptStrategy {
        match self {
            TestTime::Reference => PromptStrategy::default(),
            TestTime::Strategy(s) | TestTime::Adapt { from: s, .. } => s.clone(),
        }
    }
}

impl Adaptation {
    /// The adaptation's name, as `promptdt eval --adapt` names it: `soft-prompt`, `ptdt`, `lora`,
    /// `finetune`, `macaw`.
    pub fn name(&self) -> &'static str {
        match self {
            Adaptation::Prompt(a) => a.kind.name(),
            Adaptation::Finetune { .. } => "finetune",
            Adaptation::Macaw { .. } => "macaw",
        }
    }

    /// The same adaptation with its budget changed where given: `steps` iterations (gradient
    /// steps; PTDT's ranking steps) on batches of `batch` (demonstration segments; MACAW's
    /// transitions). `promptdt eval --adapt-steps N --adapt-batch B`, whichever the kind.
    pub fn with_budget(&self, steps: Option<usize>, batch: Option<usize>) -> Self {
        let mut out = self.clone();
        match &mut out {
            Adaptation::Prompt(a) => {
                a.steps = steps.unwrap_or(a.steps);
                a.batch = batch.unwrap_or(a.batch);
            }
            Adaptation::Finetune { steps: s, batch: b, .. } => {
                *s = steps.map_or(*s, |n| n as u64);
                *b = batch.unwrap_or(*b);
            }
            Adaptation::Macaw { steps: s, batch: b } => {
                *s = steps.unwrap_or(*s);
                *b = batch.unwrap_or(*b);
            }
        }
        out
    }

    /// What `eval_final.json`'s `adaptation` records: MACAW's budget ("2 steps on 4
    /// transitions"). The others are recorded elsewhere (`[eval.adapt]` in
    /// `eval_adapt_<kind>.json`, fine-tuning in the run's configuration), as before this value.
    pub fn recorded(&self) -> Option<String> {
        match self {
            Adaptation::Macaw { steps, batch } => {
                Some(format!("{steps} steps on {batch} transitions"))
            }
            Adaptation::Prompt(_) | Adaptation::Finetune { .. } => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::AdaptKind;

    #[test]
    fn each_method_and_setting_gives_its_test_time() {
        let mut c = TrainConfig::default();
        assert_eq!(TestTime::of(&c), TestTime::Reference);
        c.eval.prompt.strategy = pdt_prompt::PromptStrategyKind::BestReturn;
        assert_eq!(TestTime::of(&c), TestTime::Strategy(c.eval.prompt.clone()));
        c.eval.adapt.kind = AdaptKind::Lora;
        let a = TestTime::of(&c);
        assert_eq!(a.adaptation(), Some(&Adaptation::Prompt(c.eval.adapt.clone())));
        assert_eq!(a.strategy(), c.eval.prompt);
        let mut f = TrainConfig::default();
        f.run.method = Method::MtBcFinetune;
        let tt = TestTime::of(&f);
        assert!(matches!(tt.adaptation(), Some(Adaptation::Finetune { steps: 10, .. })), "{tt:?}");
        f.run.method = Method::Macaw;
        let m = TestTime::of(&f).adaptation().cloned().unwrap();
        assert_eq!(m.recorded().unwrap(), "1 steps on 256 transitions");
    }

    /// A test time written into a configuration comes back from it; one the method cannot have
    /// is refused, naming both.
    #[test]
    fn a_test_time_applies_to_the_runs_that_can_have_it() {
        let mut c = TrainConfig::default();
        let mut lora = c.eval.adapt.clone();
        lora.kind = AdaptKind::Lora;
        let strategy = PromptStrategy {
            strategy: pdt_prompt::PromptStrategyKind::BestReturn,
            ..Default::default()
        };
        let asked = [
            TestTime::Reference,
            TestTime::Strategy(strategy.clone()),
            TestTime::Adapt { from: strategy, adaptation: Adaptation::Prompt(lora.clone()) },
        ];
        for tt in &asked {
            tt.apply_to(&mut c).unwrap();
            assert_eq!(&TestTime::of(&c), tt);
        }
        let macaw = Adaptation::Macaw { steps: 1, batch: 8 };
        let tt = TestTime::Adapt { from: PromptStrategy::default(), adaptation: macaw.clone() };
        let e = tt.apply_to(&mut c).unwrap_err().to_string();
        assert!(e.contains("prompt-dt") && e.contains("macaw"), "{e}");
        let mut m = TrainConfig::default();
        m.run.method = Method::Macaw;
        tt.apply_to(&mut m).unwrap();
        assert_eq!((m.macaw.adapt_steps, m.macaw.adapt_batch), (1, 8));
        let e = TestTime::Reference.apply_to(&mut m).unwrap_err().to_string();
        assert!(e.contains("macaw") && e.contains("no adaptation"), "{e}");
        // The budget flags change whichever adaptation it is.
        let two = macaw.with_budget(Some(2), None);
        assert_eq!(two, Adaptation::Macaw { steps: 2, batch: 8 });
        let p = Adaptation::Prompt(lora).with_budget(None, Some(3));
        assert!(matches!(p, Adaptation::Prompt(ref a) if a.batch == 3), "{p:?}");
    }
}
