//! What a front end may change in an RL preset before training starts (`promptdt collect`'s
//! flags), applied in one place, as `TrainConfig::apply` does for Prompt-DT's runs.

use crate::agent::Algorithm;
use crate::train::RlConfig;

/// The settings a front end overrides; `None` keeps the preset's.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RlOverrides {
    pub seed: Option<u64>,
    pub algorithm: Option<Algorithm>,
    /// Environment steps in all. Also caps `learning_starts` at a quarter of them (the preset's
    /// rule), unless `learning_starts` is given too.
    pub total_steps: Option<u64>,
    pub learning_starts: Option<u64>,
    /// The hidden layers of both agents' networks (SAC's and TD3's).
    pub hidden: Option<Vec<i64>>,
    pub batch_size: Option<usize>,
    pub checkpoint_every: Option<u64>,
    pub tasks: Option<Vec<usize>>,
    pub sample_recent: Option<u64>,
}

impl RlConfig {
    /// Applies `o`: the step budget before `learning_starts`, so an explicit `learning_starts`
    /// wins over the quarter-of-the-budget cap. Nothing is checked here: `RlConfig::validate`
    /// checks the result against the family when training starts.
    pub fn apply(&mut self, o: &RlOverrides) {
        let RlOverrides {
            seed,
            algorithm,
            total_steps,
            learning_starts,
            hidden,
            batch_size,
            checkpoint_every,
            tasks,
            sample_recent,
        } = o;
        if let Some(s) = seed {
            self.seed = *s;
        }
        if let Some(a) = algorithm {
            self.algorithm = *a;
        }
        if let Some(s) = total_steps {
            self.total_steps = *s;
            // As the preset sets it: updates start after at most a quarter of the budget.
            self.learning_starts = self.learning_starts.min(s / 4);
        }
        if let Some(l) = learning_starts {
            self.learning_starts = *l;
        }
        if let Some(h) = hidden {
            self.agent.sac.hidden = h.clone();
            self.agent.td3.hidden = h.clone();
        }
        if let Some(b) = batch_size {
            self.batch_size = *b;
        }
        if let Some(c) = checkpoint_every {
            self.checkpoint_every = *c;
        }
        if let Some(t) = tasks {
            self.tasks = t.clone();
        }
        if let Some(w) = sample_recent {
            self.sample_recent = *w;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_given_keeps_the_preset() {
        let preset = RlConfig::preset("cheetah_vel").unwrap();
        let mut cfg = preset.clone();
        cfg.apply(&RlOverrides::default());
        assert_eq!(cfg, preset);
    }

    #[test]
    fn each_field_lands_where_it_belongs() {
        let mut cfg = RlConfig::preset("cheetah_vel").unwrap();
        let other = match cfg.algorithm {
            Algorithm::Sac => Algorithm::Td3,
            Algorithm::Td3 => Algorithm::Sac,
        };
        cfg.apply(&RlOverrides {
            seed: Some(7),
            algorithm: Some(other),
            total_steps: Some(1000),
            learning_starts: None,
            hidden: Some(vec![32, 16]),
            batch_size: Some(64),
            checkpoint_every: Some(500),
            tasks: Some(vec![2, 5]),
            sample_recent: Some(300),
        });
        assert_eq!((cfg.seed, cfg.algorithm, cfg.total_steps), (7, other, 1000));
        // The preset's 5000 capped at a quarter of the new budget.
        assert_eq!(cfg.learning_starts, 250);
        assert_eq!((&cfg.agent.sac.hidden, &cfg.agent.td3.hidden), (&vec![32, 16], &vec![32, 16]));
        assert_eq!((cfg.batch_size, cfg.checkpoint_every, cfg.sample_recent), (64, 500, 300));
        assert_eq!(cfg.tasks, vec![2, 5]);
    }

    #[test]
    fn an_explicit_learning_start_wins_over_the_cap() {
        let mut cfg = RlConfig::preset("cheetah_vel").unwrap();
        cfg.apply(&RlOverrides {
            total_steps: Some(1000),
            learning_starts: Some(900),
            ..RlOverrides::default()
        });
        assert_eq!((cfg.total_steps, cfg.learning_starts), (1000, 900));
    }
}
