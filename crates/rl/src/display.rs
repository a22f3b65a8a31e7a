//! What `promptdt collect` and `promptdt agent combine` print, as `Display`: the library's
//! summaries say themselves, so the command only prints them.

use crate::datasets::DatasetSummary;
use crate::train::{AgentCard, TrainProgress};
use pdt_data::mode::Mode;
use std::fmt;

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// A `Display` made of a closure, for the views below that borrow a summary.
struct View<F: Fn(&mut fmt::Formatter<'_>) -> fmt::Result>(F);

impl<F: Fn(&mut fmt::Formatter<'_>) -> fmt::Result> fmt::Display for View<F> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        (self.0)(f)
    }
}

impl AgentCard {
    /// After training: the algorithm, the budget, and the snapshots picked as expert and medium
    /// with their mean returns (and a random policy's, for scale).
    pub fn training_summary(&self) -> impl fmt::Display + '_ {
        View(move |f: &mut fmt::Formatter<'_>| {
            write!(
                f,
                "trained {} on {} for {} steps in {:.0} s; expert: step {} (mean {:.1}), medium: \
                 step {} (mean {:.1}), random: mean {:.1}",
                self.algorithm.name(),
                self.family,
                self.config.total_steps,
                self.wall_seconds,
                self.expert_step,
                mean(&self.expert_eval),
                self.medium_step,
                mean(&self.medium_eval),
                mean(&self.random_eval),
            )
        })
    }

    /// A combined agent's experts, one line per task, then their mean return (no newline at the
    /// end, so a caller can append where it wrote the card).
    pub fn experts_table(&self) -> impl fmt::Display + '_ {
        View(move |f: &mut fmt::Formatter<'_>| {
            writeln!(f, "{:<6} {:>12} {:>10} {:>10}  file", "task", "return", "step", "mirror")?;
            for e in &self.task_experts {
                let m = e.mirror.as_deref().unwrap_or("-");
                writeln!(
                    f,
                    "{:<6} {:>12.1} {:>10} {m:>10}  {}",
                    e.task, e.eval_return, e.step, e.file
                )?;
            }
            let n = self.expert_eval.len();
            write!(f, "mean expert return {:.1} over {n} tasks", mean(&self.expert_eval))
        })
    }
}

impl TrainProgress<'_> {
    /// The progress bar's message: the recent mean return, per task where they fit on a line
    /// (else the worst and the best task), and the critic's last loss.
    pub fn message(&self) -> String {
        let seen: Vec<f64> = self.recent.iter().flatten().copied().collect();
        let per_task = if self.recent.len() <= 4 {
            let task = |(i, r): (usize, &Option<f64>)| match r {
                Some(r) => format!("t{i} {r:.0}"),
                None => format!("t{i} -"),
            };
            self.recent.iter().enumerate().map(task).collect::<Vec<_>>().join(" ")
        } else {
            // Too many tasks for one line: the worst and the best, with their indices.
            let known = self.recent.iter().enumerate().filter_map(|(i, r)| r.map(|r| (i, r)));
            let worst = known.clone().min_by(|a, b| a.1.total_cmp(&b.1));
            let best = known.max_by(|a, b| a.1.total_cmp(&b.1));
            match (worst, best) {
                (Some((wi, w)), Some((bi, b))) => format!(
                    "worst t{wi} {w:.0}, best t{bi} {b:.0}, {}/{} tasks seen",
                    seen.len(),
                    self.recent.len()
                ),
                _ => "no episode yet".to_string(),
            }
        };
        format!("return {:.1} ({per_task}) q-loss {:.3}", mean(&seen), self.last_update.critic_loss)
    }
}

/// The datasets written: per task, the mean return of each mode's dataset and of the expert
/// prompts; then how much was written, where the card is (no newline at the end).
impl fmt::Display for DatasetSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let head = ["task", "expert", "medium", "random", "prompt-expert"];
        writeln!(
            f,
            "{:<6} {:>12} {:>12} {:>12} {:>14}",
            head[0], head[1], head[2], head[3], head[4]
        )?;
        let mut tasks: Vec<usize> = self.entries.iter().map(|e| e.task).collect();
        tasks.sort_unstable();
        tasks.dedup();
        let dataset =
            |t: usize, m| self.get(t, m).map_or("-".into(), |e| format!("{:.1}", e.dataset.mean));
        for &t in &tasks {
            let p =
                self.get(t, Mode::Expert).map_or("-".into(), |e| format!("{:.1}", e.prompts.mean));
            writeln!(
                f,
                "{:<6} {:>12} {:>12} {:>12} {:>14}",
                t,
                dataset(t, Mode::Expert),
                dataset(t, Mode::Medium),
                dataset(t, Mode::Random),
                p
            )?;
        }
        write!(f, "wrote {} files ({} steps) and {}", self.files, self.steps, self.card.display())
    }
}
