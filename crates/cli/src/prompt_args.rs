//! The parsers of the test-time prompt flags of `promptdt eval` and `promptdt serve`
//! (docs/prompt-control.md) into `pdt_prompt`'s types, the one owner of prompt strategies.

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
