//! Which trajectories history segments are drawn from, and with what weight
//! (`process_dataset`, `promptdt-reference.md` b.3).

use crate::config::TrajectoryRanking;
use pdt_data::TaskDataset;

/// Kept trajectory indices with cumulative sampling weights (proportional to length).
#[derive(Debug, Clone, PartialEq)]
pub struct Ranking {
    /// Indices into `TaskDataset::trajectories`, from the best kept return to the worst kept.
    pub kept: Vec<usize>,
    /// Cumulative weights, same order as `kept`; the last entry is 1.
    cumulative: Vec<f64>,
}

impl Ranking {
    pub fn new(ds: &TaskDataset, rule: TrajectoryRanking) -> Self {
        let returns = ds.returns();
        let lens: Vec<usize> = ds.trajectories.iter().map(|t| t.len()).collect();
        // Ascending by return, like `np.argsort(returns)`; ties keep dataset order (a stable sort;
        // numpy's default sort is not stable, so tied trajectories may be ranked differently there).
        let mut sorted: Vec<usize> = (0..returns.len()).collect();
        sorted.sort_by(|&a, &b| returns[a].total_cmp(&returns[b]));
        let total: usize = lens.iter().sum();
        let best_first = sorted.iter().rev().copied();
        let kept: Vec<usize> = match rule {
            TrajectoryRanking::All => best_first.collect(),
            TrajectoryRanking::ReferenceOffByOne => {
                // Reference loop: start with the best trajectory, then add the next best while the
                // kept steps stay *strictly* below the total; the worst one would reach the total
                // exactly, so it is never added.
                let mut kept = Vec::new();
                let mut steps = 0usize;
                for i in best_first {
                    if kept.is_empty() || steps + lens[i] < total {
                        steps += lens[i];
                        kept.push(i);
                    } else {
                        break;
                    }
                }
                kept
            }
        };
        let kept_steps: usize = kept.iter().map(|&i| lens[i]).sum();
        let mut acc = 0usize;
        let cumulative = kept
            .iter()
            .map(|&i| {
                acc += lens[i];
                acc as f64 / kept_steps as f64
            })
            .collect();
        Self { kept, cumulative }
    }

    /// Draws a trajectory index given `u ~ U[0, 1)`, with probability proportional to length.
    pub fn pick(&self, u: f64) -> usize {
        let pos = self.cumulative.partition_point(|&c| c <= u).min(self.kept.len() - 1);
        self.kept[pos]
    }

    /// Sampling probability of each trajectory of the dataset (0 for the excluded ones).
    pub fn probabilities(&self, num_trajectories: usize) -> Vec<f64> {
        let mut p = vec![0.0; num_trajectories];
        let mut prev = 0.0;
        for (&i, &c) in self.kept.iter().zip(&self.cumulative) {
            p[i] = c - prev;
            prev = c;
        }
        p
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pdt_data::Trajectory;

    fn ds(returns_and_lens: &[(f32, usize)]) -> TaskDataset {
        let trajs = returns_and_lens
            .iter()
            .map(|&(ret, t)| {
                let mut r = vec![0.0; t];
                r[0] = ret;
                Trajectory::new(1, 1, vec![0.0; t], vec![0.0; t], r, vec![false; t], vec![false; t])
                    .unwrap()
            })
            .collect();
        TaskDataset::new(trajs).unwrap()
    }

    #[test]
    fn reference_rule_drops_exactly_the_lowest_return_trajectory() {
        let d = ds(&[(5.0, 10), (1.0, 10), (9.0, 10), (3.0, 10)]);
        let r = Ranking::new(&d, TrajectoryRanking::ReferenceOffByOne);
        assert_eq!(r.kept, vec![2, 0, 3]); // best first; index 1 (return 1.0) excluded
        let p = r.probabilities(4);
        for (got, want) in p.iter().zip([1.0 / 3.0, 0.0, 1.0 / 3.0, 1.0 / 3.0]) {
            assert!((got - want).abs() < 1e-12, "{p:?}");
        }
        let all = Ranking::new(&d, TrajectoryRanking::All);
        assert_eq!(all.kept, vec![2, 0, 3, 1]);
    }

    #[test]
    fn weights_are_proportional_to_length_and_single_trajectory_is_kept() {
        let d = ds(&[(5.0, 30), (1.0, 10), (9.0, 10)]);
        let r = Ranking::new(&d, TrajectoryRanking::ReferenceOffByOne);
        assert_eq!(r.kept, vec![2, 0]);
        let p = r.probabilities(3);
        assert!((p[0] - 0.75).abs() < 1e-12 && (p[2] - 0.25).abs() < 1e-12 && p[1] == 0.0);
        assert_eq!(r.pick(0.0), 2);
        assert_eq!(r.pick(0.2499), 2);
        assert_eq!(r.pick(0.25), 0);
        assert_eq!(r.pick(0.999_999), 0);
        let one = ds(&[(1.0, 5)]);
        assert_eq!(Ranking::new(&one, TrajectoryRanking::ReferenceOffByOne).kept, vec![0]);
    }
}
