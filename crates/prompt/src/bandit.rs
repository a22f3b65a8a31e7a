//! The `bandit` prompt strategy: a multi-armed bandit over a test task's candidate prompt
//! segments, updated from episode returns (Rietz, Smirnov, Karimi, Cao 2025, arXiv 2502.04979;
//! code `sarakarimi/prompt-dt`, `prompt_dt/prompt_tuning_bandit.py`).
//!
//! As in the paper, each of the J prompt slots has its own reward estimate per arm, every arm is
//! a candidate segment of the task's demonstrations, and the reward of a pull is the episode's
//! return. The paper estimates rewards with one small neural network per slot (NeuralUCB-like,
//! on the raw segment or on transformer features); here each slot keeps the **mean return per
//! arm** (a tabular bandit). That is the choice `docs/prompt-control.md` records: the estimator
//! has no hyper-parameters of its own and no learning loop, and with an evaluation's few
//! episodes per task a network over segments has little to fit. The selection rule is the
//! paper's epsilon-greedy (all slots explore together with probability epsilon, decayed by
//! `epsilon_decay` per round, or linearly to 0 over `explore_fraction` of the rounds as the cited
//! code's schedule does), or UCB1 as an option.

use crate::strategy::{BanditConfig, BanditRule, SegmentChoice};
use crate::Rng;
use rand::Rng as _;

/// Pulls and summed reward of one arm in one slot.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct ArmStats {
    pulls: u64,
    total: f64,
}

impl ArmStats {
    fn mean(&self) -> Option<f64> {
        (self.pulls > 0).then(|| self.total / self.pulls as f64)
    }
}

/// What one round chose.
#[derive(Debug, Clone, PartialEq)]
pub struct BanditChoice {
    /// Arm (index into [`SegmentBandit::arms`]) of each slot.
    pub arms: Vec<usize>,
    /// Whether the round explored (epsilon-greedy's random pull, or an untried arm under UCB).
    pub explored: bool,
}

/// A bandit over `arms` for a prompt of `slots` segments.
#[derive(Debug, Clone)]
pub struct SegmentBandit {
    cfg: BanditConfig,
    arms: Vec<SegmentChoice>,
    /// `[slots][arms]`
    stats: Vec<Vec<ArmStats>>,
    epsilon: f64,
    /// Set by [`Self::plan_rounds`] with `explore_fraction`: the number of rounds over which
    /// epsilon falls linearly to 0 (else it falls by `epsilon_decay` per round).
    decay_rounds: Option<f64>,
    rounds: u64,
    /// Smallest and largest reward seen (UCB scales its bonus by their difference).
    range: Option<(f64, f64)>,
}

impl SegmentBandit {
    /// `None` when there is no arm or no slot.
    pub fn new(cfg: BanditConfig, arms: Vec<SegmentChoice>, slots: usize) -> Option<Self> {
        if arms.is_empty() || slots == 0 {
            return None;
        }
        let stats = vec![vec![ArmStats::default(); arms.len()]; slots];
        Some(Self {
            epsilon: cfg.epsilon,
            decay_rounds: None,
            cfg,
            arms,
            stats,
            rounds: 0,
            range: None,
        })
    }

    /// Tells the bandit how many rounds it will play: with `explore_fraction` f set, epsilon then
    /// falls by `epsilon / (f x rounds)` per round, reaching 0 after the first f of them (the
    /// cited code's `epsilon_decay = 1 / (num_rollouts x 0.2)` with epsilon 1.0). Without it,
    /// nothing changes.
    pub fn plan_rounds(&mut self, rounds: usize) {
        if let Some(f) = self.cfg.explore_fraction {
            self.decay_rounds = Some((f * rounds as f64).max(1.0));
        }
    }

    /// Whether the settings need [`Self::plan_rounds`] (`explore_fraction` is set).
    pub fn needs_rounds(cfg: &BanditConfig) -> bool {
        cfg.explore_fraction.is_some()
    }

    pub fn arms(&self) -> &[SegmentChoice] {
        &self.arms
    }

    /// The segments of a choice, in slot order.
    pub fn segments(&self, choice: &BanditChoice) -> Vec<SegmentChoice> {
        choice.arms.iter().map(|&a| self.arms[a]).collect()
    }

    /// The best arm by mean return, per slot (untried arms last; ties: the lower index).
    fn greedy(&self, slot: usize) -> usize {
        let mut best: Option<(usize, f64)> = None;
        for (a, s) in self.stats[slot].iter().enumerate() {
            if let Some(m) = s.mean() {
                if best.is_none_or(|(_, b)| m > b) {
                    best = Some((a, m));
                }
            }
        }
        best.map_or(0, |(a, _)| a)
    }

    /// This round's arm per slot.
    pub fn choose(&mut self, rng: &mut Rng) -> BanditChoice {
        let n = self.arms.len();
        let slots = self.stats.len();
        match self.cfg.rule {
            BanditRule::EpsilonGreedy => {
                // Nothing tried yet: the greedy arm would be arm 0 by index only, so explore.
                let untried = self.rounds == 0;
                // The paper draws the exploration coin first, then the arms.
                let explore = rng.random::<f64>() < self.epsilon || untried;
                let arms = if explore {
                    (0..slots).map(|_| rng.random_range(0..n)).collect()
                } else {
                    (0..slots).map(|s| self.greedy(s)).collect()
                };
                BanditChoice { arms, explored: explore }
            }
            BanditRule::Ucb => {
                let mut explored = false;
                let width = self.range.map_or(0.0, |(lo, hi)| hi - lo).max(f64::MIN_POSITIVE);
                let arms = (0..slots)
                    .map(|s| {
                        let stats = &self.stats[s];
                        // Untried arms first, a uniformly drawn one each time (a seeded random
                        // order): by index, with more arms than rounds UCB would sweep the first
                        // demonstration from its first step and never see the others.
                        let untried: Vec<usize> = (0..n).filter(|&a| stats[a].pulls == 0).collect();
                        if !untried.is_empty() {
                            explored = true;
                            return untried[rng.random_range(0..untried.len())];
                        }
                        let total: u64 = stats.iter().map(|st| st.pulls).sum();
                        let ln = (total as f64).ln();
                        let score = |st: &ArmStats| {
                            st.total / st.pulls as f64
                                + self.cfg.ucb_c * width * (2.0 * ln / st.pulls as f64).sqrt()
                        };
                        let mut best = (0, f64::NEG_INFINITY);
                        for (a, st) in stats.iter().enumerate() {
                            let v = score(st);
                            if v > best.1 {
                                best = (a, v);
                            }
                        }
                        best.0
                    })
                    .collect();
                BanditChoice { arms, explored }
            }
        }
    }

    /// Records the returns of the episodes that used `choice` (every slot's arm earns each
    /// return), then ends the round (epsilon decays).
    pub fn update(&mut self, choice: &BanditChoice, returns: &[f64]) {
        for &r in returns.iter().filter(|r| r.is_finite()) {
            for (slot, &a) in choice.arms.iter().enumerate() {
                let st = &mut self.stats[slot][a];
                st.pulls += 1;
                st.total += r;
            }
            self.range = Some(match self.range {
                None => (r, r),
                Some((lo, hi)) => (lo.min(r), hi.max(r)),
            });
        }
        self.rounds += 1;
        self.epsilon = match self.decay_rounds {
            // In closed form, so that it reaches exactly 0 where the schedule ends.
            Some(d) => (self.cfg.epsilon * (1.0 - self.rounds as f64 / d)).max(0.0),
            None => (self.epsilon - self.cfg.epsilon_decay).max(0.0),
        };
    }

    /// The exploration probability of the next round.
    pub fn epsilon(&self) -> f64 {
        self.epsilon
    }

    /// Mean return of each arm in `slot` (`None`: never pulled).
    pub fn means(&self, slot: usize) -> Vec<Option<f64>> {
        self.stats[slot].iter().map(ArmStats::mean).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn arms(n: usize) -> Vec<SegmentChoice> {
        (0..n).map(|i| SegmentChoice { demo: i, start: 0 }).collect()
    }

    /// Arm `a` pays `a` plus noise in [-2, 2]: arm n-1 is best.
    fn pull(arms_chosen: &[usize], rng: &mut Rng) -> f64 {
        let a = arms_chosen[0] as f64;
        a + rng.random_range(-2.0..2.0)
    }

    fn run(rule: BanditRule, rounds: usize, seed: u64) -> (SegmentBandit, Vec<usize>) {
        // UCB1's textbook coefficient (1 x the reward range) explores for long; 0.2 settles in 600.
        let cfg = BanditConfig { rule, epsilon: 0.2, ucb_c: 0.2, ..BanditConfig::default() };
        let mut b = SegmentBandit::new(cfg, arms(6), 1).unwrap();
        let (mut rng, mut env) = (Rng::seed_from_u64(seed), Rng::seed_from_u64(seed + 100));
        let mut picks = Vec::new();
        for _ in 0..rounds {
            let c = b.choose(&mut rng);
            let r = pull(&c.arms, &mut env);
            b.update(&c, &[r]);
            picks.push(c.arms[0]);
        }
        (b, picks)
    }

    #[test]
    fn epsilon_greedy_and_ucb_converge_to_the_best_arm() {
        for rule in [BanditRule::EpsilonGreedy, BanditRule::Ucb] {
            let (b, picks) = run(rule, 600, 3);
            let last = &picks[400..];
            let best = last.iter().filter(|&&a| a == 5).count();
            assert!(best as f64 > 0.75 * last.len() as f64, "{rule:?}: {best} of {}", last.len());
            let means = b.means(0);
            assert!(means[5].unwrap() > means[0].unwrap_or(f64::NEG_INFINITY));
        }
    }

    #[test]
    fn ucb_tries_every_arm_first_and_choices_are_seeded() {
        let (_, picks) = run(BanditRule::Ucb, 6, 1);
        let mut first = picks.clone();
        first.sort();
        assert_eq!(first, vec![0, 1, 2, 3, 4, 5]);
        assert_eq!(
            run(BanditRule::EpsilonGreedy, 50, 7).1,
            run(BanditRule::EpsilonGreedy, 50, 7).1
        );
        assert_ne!(
            run(BanditRule::EpsilonGreedy, 50, 7).1,
            run(BanditRule::EpsilonGreedy, 50, 8).1
        );
    }

    #[test]
    fn ucb_tries_untried_arms_in_a_seeded_random_order() {
        let cfg = BanditConfig { rule: BanditRule::Ucb, ..BanditConfig::default() };
        let order = |seed: u64| {
            let mut b = SegmentBandit::new(cfg.clone(), arms(50), 1).unwrap();
            let mut rng = Rng::seed_from_u64(seed);
            (0..5)
                .map(|_| {
                    let c = b.choose(&mut rng);
                    assert!(c.explored);
                    b.update(&c, &[1.0]);
                    c.arms[0]
                })
                .collect::<Vec<_>>()
        };
        // Reproducible from the seed, differs across seeds, and is not the index order.
        assert_eq!(order(4), order(4));
        assert_ne!(order(4), order(5));
        assert!((0..8).any(|s| order(s) != vec![0, 1, 2, 3, 4]));
        let mut first = order(6);
        first.sort_unstable();
        first.dedup();
        assert_eq!(first.len(), 5, "an arm tried twice before every arm was tried: {first:?}");
    }

    #[test]
    fn explore_fraction_decays_epsilon_to_zero_over_that_share_of_the_rounds() {
        // The cited code: epsilon 1.0 to 0 over the first 20 % of 50 rollouts: 10 rounds.
        let cfg =
            BanditConfig { epsilon: 1.0, explore_fraction: Some(0.2), ..BanditConfig::default() };
        assert!(SegmentBandit::needs_rounds(&cfg));
        let mut b = SegmentBandit::new(cfg, arms(4), 1).unwrap();
        b.plan_rounds(50);
        let mut rng = Rng::seed_from_u64(0);
        let mut eps = Vec::new();
        for _ in 0..12 {
            eps.push(b.epsilon());
            let c = b.choose(&mut rng);
            b.update(&c, &[c.arms[0] as f64]);
        }
        assert_eq!(eps[0], 1.0);
        assert!((eps[5] - 0.5).abs() < 1e-12, "{eps:?}");
        assert!(eps[9] > 0.0 && eps[10] == 0.0 && eps[11] == 0.0, "{eps:?}");
        // Greedy from then on: the best arm tried so far, every round.
        let picks: Vec<bool> = (0..10).map(|_| b.choose(&mut rng).explored).collect();
        assert!(picks.iter().all(|e| !e), "{picks:?}");
        // Without the fraction, plan_rounds changes nothing: `epsilon_decay` (0) holds.
        let mut b = SegmentBandit::new(BanditConfig::default(), arms(4), 1).unwrap();
        b.plan_rounds(50);
        let c = b.choose(&mut rng);
        b.update(&c, &[1.0]);
        assert_eq!(b.epsilon(), BanditConfig::default().epsilon);
    }

    #[test]
    fn slots_learn_separately_and_epsilon_decays() {
        let cfg = BanditConfig { epsilon: 1.0, epsilon_decay: 0.5, ..BanditConfig::default() };
        let mut b = SegmentBandit::new(cfg, arms(3), 2).unwrap();
        let c = BanditChoice { arms: vec![2, 0], explored: false };
        b.update(&c, &[10.0, 20.0]);
        assert_eq!(b.means(0), vec![None, None, Some(15.0)]);
        assert_eq!(b.means(1), vec![Some(15.0), None, None]);
        b.update(&c, &[]);
        // epsilon 1 -> 0.5 -> 0: now always greedy
        let mut rng = Rng::seed_from_u64(0);
        for _ in 0..20 {
            let c = b.choose(&mut rng);
            assert_eq!((c.arms.clone(), c.explored), (vec![2, 0], false));
        }
        assert!(SegmentBandit::new(BanditConfig::default(), vec![], 1).is_none());
    }
}
