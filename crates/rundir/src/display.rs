//! What `promptdt eval` prints, as `Display` of the evaluation's files: the per-task table, the
//! adaptation's log and the choices of a prompt strategy.

use crate::files::{FinalEval, PromptEval};
use std::fmt;

/// Per task: mean and spread of the return over its episodes (and the success rate where the
/// family has a success criterion, as Meta-World does), then the average; then the adaptation,
/// where there was one. No newline at the end.
impl fmt::Display for FinalEval {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let rates: Option<Vec<f64>> = self.tasks.iter().map(|t| t.success_rate).collect();
        let rates = rates.filter(|v| !v.is_empty());
        let success_col = |x: Option<f64>| match (&rates, x) {
            (Some(_), Some(v)) => format!(" {:>8.1}%", 100.0 * v),
            _ => String::new(),
        };
        let head = if rates.is_some() { format!(" {:>9}", "success") } else { String::new() };
        writeln!(f, "{:<24} {:>12} {:>10} {:>9}{head}", "task", "return mean", "std", "episodes")?;
        for t in &self.tasks {
            let (mean, std, n) = (t.return_mean, t.return_std, t.episodes);
            let rate = success_col(t.success_rate);
            writeln!(f, "{:<24} {mean:>12.2} {std:>10.2} {n:>9}{rate}", t.task)?;
        }
        let mean_rate = rates.as_ref().map(|v| v.iter().sum::<f64>() / v.len() as f64);
        let average = format!("average ({})", self.eval_on);
        let rate = success_col(mean_rate);
        write!(f, "{average:<24} {:>12.2} {:>10} {:>9}{rate}", self.mean_return, "", "")?;
        if let Some(how) = &self.adaptation {
            write!(f, "\nadapted to each task with {how}")?;
        }
        Ok(())
    }
}

impl PromptEval {
    /// The file of the run directory this evaluation is written to: `eval_final.json` for the
    /// reference rule, else the adaptation's or the prompt strategy's own.
    pub fn file_name(&self) -> String {
        if !self.adapt.is_none() {
            format!("eval_adapt_{}.json", self.adapt.kind)
        } else if self.prompt_strategy.is_default() {
            crate::EVAL_FINAL_JSON.to_string()
        } else {
            format!("eval_prompt_{}.json", self.prompt_strategy.strategy)
        }
    }
}

/// The table, each task's adaptation (its action loss before and after), what chose the prompts,
/// and the checkpoint evaluated. No newline at the end.
impl fmt::Display for PromptEval {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{}", self.eval)?;
        for l in &self.adapt_log {
            writeln!(
                f,
                "adapted {:<24} action loss {:.5} -> {:.5} ({} steps, {} values, {:.2} s)",
                l.task, l.loss_before, l.loss_after, l.steps, l.trainable, l.seconds
            )?;
        }
        if !self.adapt.is_none() {
            writeln!(f, "adaptation {} (eval.adapt)", self.adapt.kind)?;
        } else if !self.prompt_strategy.is_default() {
            let (s, n) = (&self.prompt_strategy.strategy, self.picks.len());
            writeln!(f, "prompt strategy {s} ({n} choices logged)")?;
        }
        write!(f, "checkpoint {} (iteration {})", self.eval.checkpoint, self.eval.iteration)
    }
}
