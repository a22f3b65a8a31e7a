//! [`TestTime`]: what an evaluation does besides acting with the trained weights, as one value:
//! the reference rule, another prompt strategy, or an adaptation to each test task (`[eval.adapt]`'s
//! soft prompt, PTDT and LoRA, MT-BC-Finetune's fine-tuning, MACAW's gradient steps). A learner's
//! evaluation takes it (`pdt_train`'s `Learner::evaluate`), so no learner decides by its method
//! or its configuration which of them runs.

use super::{AdaptConfig, Method, TrainConfig};
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
}
