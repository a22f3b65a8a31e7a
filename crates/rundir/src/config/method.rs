//! [`Method`]: the methods of the paper's comparison and every capability the other crates ask
//! of one. A new method is a variant here with its line in each table, its module and one arm in
//! the registry (`pdt_train::methods`); `docs/adding-a-method.md`.

use super::{LEGACY_LOSS_METRIC, LEGACY_MACAW_LOSS_METRIC};
use serde::{Deserialize, Serialize};

/// The methods of the paper's comparison.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Prompt-DT: prompt + returns-to-go.
    #[default]
    PromptDt,
    /// Prompt-MT-BC: prompt, history returns-to-go zeroed in training (`--no-rtg --no-r`).
    PromptMtBc,
    /// MT-ORL: returns-to-go, no prompt (`--no-prompt`).
    MtOrl,
    /// MT-BC-Finetune: no prompt, no returns-to-go; fine-tuned on each test task's demonstrations
    /// before evaluation (`--no-prompt --no-rtg --no-r --finetune`).
    MtBcFinetune,
    /// MACAW (Mitchell et al. 2021): meta-learned value function and policy, adapted to each test
    /// task's data with a few gradient steps (`[macaw]` section; `crates/macaw`).
    Macaw,
}

/// The one list of methods and what each is: the front ends, the report, the reproduction
/// manifests and the pack ask these instead of naming methods. Every capability is an exhaustive
/// `match` (no `_` arm, no negated `matches!`), so a new variant does not compile until each
/// table says what it is; the tests below check that [`Method::ALL`] lists every variant, and
/// `pdt_train::methods`' that the registry builds each (`docs/adding-a-method.md`).
impl Method {
    /// Every method, in the order the paper lists them (the report's order and plot colours).
    pub const ALL: [Method; 5] =
        [Method::PromptDt, Method::PromptMtBc, Method::MtOrl, Method::MtBcFinetune, Method::Macaw];

    /// Whether the method conditions on a prompt (a demonstration segment of the task).
    pub fn uses_prompt(self) -> bool {
        match self {
            Method::PromptDt | Method::PromptMtBc => true,
            Method::MtOrl | Method::MtBcFinetune | Method::Macaw => false,
        }
    }

    /// Whether the history's returns-to-go are zeroed in training (the behaviour-cloning variants).
    pub fn zeroes_history_returns(self) -> bool {
        match self {
            Method::PromptMtBc | Method::MtBcFinetune => true,
            Method::PromptDt | Method::MtOrl | Method::Macaw => false,
        }
    }

    /// Prompt-DT and its variants: the Decision Transformer, configured by the `[model]`,
    /// `[optimizer]` and `[sampler]` sections and served by `pdt-policy`. MACAW has networks of
    /// its own (its `[macaw]` section).
    pub fn is_transformer(self) -> bool {
        match self {
            Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune => true,
            Method::Macaw => false,
        }
    }

    /// Whether the method adapts to each test task (fine-tuning, MACAW's gradient steps) before
    /// it acts there: its test-time policy is not the checkpoint as saved, so it is not served.
    pub fn adapts_before_acting(self) -> bool {
        match self {
            Method::MtBcFinetune | Method::Macaw => true,
            Method::PromptDt | Method::PromptMtBc | Method::MtOrl => false,
        }
    }

    /// Whether runs of the method can train together in a pack (`docs/packs.md`): the
    /// transformer variants, which share one model shape and one batched step. A pack refuses
    /// any other method by name rather than training it as something else.
    pub fn packs(self) -> bool {
        match self {
            Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune => true,
            Method::Macaw => false,
        }
    }

    /// The method's own section of `config.toml`, written only for runs of the method.
    pub fn section(self) -> Option<&'static str> {
        match self {
            Method::Macaw => Some("macaw"),
            Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune => None,
        }
    }

    /// The `metrics.jsonl` column of the training loss in runs written before `run.json`
    /// recorded it.
    pub fn legacy_loss_metric(self) -> &'static str {
        match self {
            Method::Macaw => LEGACY_MACAW_LOSS_METRIC,
            Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune => {
                LEGACY_LOSS_METRIC
            }
        }
    }

    /// The method's name in the paper and in messages ("MACAW").
    pub fn title(self) -> &'static str {
        match self {
            Method::PromptDt => "Prompt-DT",
            Method::PromptMtBc => "Prompt-MT-BC",
            Method::MtOrl => "MT-ORL",
            Method::MtBcFinetune => "MT-BC-Finetune",
            Method::Macaw => "MACAW",
        }
    }

    /// The method's name in `config.toml`, `run.json` and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Method::PromptDt => "prompt-dt",
            Method::PromptMtBc => "prompt-mt-bc",
            Method::MtOrl => "mt-orl",
            Method::MtBcFinetune => "mt-bc-finetune",
            Method::Macaw => "macaw",
        }
    }

    /// The names of the methods that have `capability`, in [`Method::ALL`]'s order, for
    /// messages ("prompt-dt and prompt-mt-bc"), so no message lists methods by hand.
    pub fn names_where(capability: fn(Method) -> bool) -> String {
        let names: Vec<&str> =
            Method::ALL.into_iter().filter(|m| capability(*m)).map(Method::name).collect();
        match names.split_last() {
            Some((last, rest)) if !rest.is_empty() => format!("{} and {last}", rest.join(", ")),
            _ => names.join(""),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Method;
    use crate::config::TrainConfig;

    /// The variants declared in this file's `pub enum Method`, read from the source: the compiler
    /// checks that each table covers every variant, this that [`Method::ALL`] does (no front end
    /// would offer a variant missing there).
    fn declared_variants() -> Vec<String> {
        let src = include_str!("method.rs");
        let body = src.split("pub enum Method {").nth(1).unwrap().split("\n}").next().unwrap();
        body.lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with("//") && !l.starts_with("#["))
            .map(|l| l.trim_end_matches(',').to_string())
            .collect()
    }

    #[test]
    fn all_lists_every_declared_variant_in_order() {
        let declared = declared_variants();
        assert!(declared.len() >= 5, "{declared:?}: the enum was not found");
        let listed: Vec<String> = Method::ALL.iter().map(|m| format!("{m:?}")).collect();
        assert_eq!(listed, declared, "Method::ALL must list every variant in declaration order");
    }

    #[test]
    fn every_method_has_one_name_that_parses_and_serialises_back() {
        let mut names = std::collections::BTreeSet::new();
        let mut titles = std::collections::BTreeSet::new();
        for m in Method::ALL {
            assert!(names.insert(m.name()) && titles.insert(m.title()), "{m:?}: a name twice");
            assert_eq!(m.name().parse::<Method>().unwrap(), m);
            let toml = format!("[run]\nmethod = \"{}\"\n", m.name());
            let c: TrainConfig = toml::from_str(&toml).unwrap();
            assert_eq!(c.run.method, m);
        }
    }

    /// The tables agree with one another: what acts through the transformer may take a prompt
    /// and pack; what does not has its own section (its networks' settings), which the
    /// configuration writes for its runs alone.
    #[test]
    fn the_capability_tables_agree() {
        for m in Method::ALL {
            if !m.is_transformer() {
                assert!(m.section().is_some(), "{m:?}: its own networks need their section");
                assert!(!m.uses_prompt() && !m.packs(), "{m:?}");
            }
            let mut c = TrainConfig::default();
            c.run.method = m;
            let v = c.to_toml_value().unwrap();
            for other in Method::ALL.into_iter().filter_map(Method::section) {
                let written = v.get(other).is_some();
                assert_eq!(written, m.section() == Some(other), "{m:?}: section [{other}]");
            }
            assert!(!m.legacy_loss_metric().is_empty());
        }
    }

    #[test]
    fn names_where_lists_in_order() {
        assert_eq!(Method::names_where(Method::uses_prompt), "prompt-dt and prompt-mt-bc");
        assert_eq!(Method::names_where(|m| m == Method::Macaw), "macaw");
        assert_eq!(
            Method::names_where(Method::packs),
            "prompt-dt, prompt-mt-bc, mt-orl and mt-bc-finetune"
        );
    }
}
