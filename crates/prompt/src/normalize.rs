//! Global state normalisation (`promptdt-reference.md` b.2).

use pdt_data::TaskDataset;
use serde::{Deserialize, Serialize};

/// Per-dimension state mean and std. States are normalised as `(s - mean) / std`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StateNorm {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
}

impl StateNorm {
    /// Identity normalisation (mean 0, std 1): the reference's `--no_state_normalize`.
    pub fn identity(obs_dim: usize) -> Self {
        Self { mean: vec![0.0; obs_dim], std: vec![1.0; obs_dim] }
    }

    /// Mean and population std (+1e-6) over every observation of `datasets`, as the reference's
    /// `process_total_data_mean` (a dataset passed twice counts twice, as in the reference).
    ///
    /// Sums are accumulated in f64 and rounded to f32; numpy sums float32 pairwise, so the two agree
    /// to about 1e-7 relative, not bitwise.
    pub fn from_datasets<'a>(
        obs_dim: usize,
        datasets: impl IntoIterator<Item = &'a TaskDataset>,
    ) -> Self {
        let mut n = 0usize;
        let mut sum = vec![0f64; obs_dim];
        let all: Vec<&TaskDataset> = datasets.into_iter().collect();
        let rows = || {
            all.iter()
                .flat_map(|d| d.trajectories.iter())
                .flat_map(|t| t.observations.chunks_exact(obs_dim))
        };
        for row in rows() {
            n += 1;
            for (acc, &x) in sum.iter_mut().zip(row) {
                *acc += x as f64;
            }
        }
        if n == 0 {
            return Self::identity(obs_dim);
        }
        let mean: Vec<f64> = sum.iter().map(|s| s / n as f64).collect();
        let mut sq = vec![0f64; obs_dim];
        for row in rows() {
            for ((acc, &x), m) in sq.iter_mut().zip(row).zip(&mean) {
                *acc += (x as f64 - m).powi(2);
            }
        }
        Self {
            mean: mean.iter().map(|&m| m as f32).collect(),
            std: sq.iter().map(|&s| ((s / n as f64).sqrt() as f32) + 1e-6).collect(),
        }
    }

    /// Normalises one state value of dimension `j`. Computed in f64 and rounded, as numpy does it
    /// (the reference pads with float64 zeros, which promotes the whole segment to float64).
    #[inline]
    pub fn apply(&self, j: usize, x: f32) -> f32 {
        ((x as f64 - self.mean[j] as f64) / self.std[j] as f64) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pdt_data::Trajectory;

    fn traj(obs: Vec<f32>) -> Trajectory {
        let t = obs.len() / 2;
        Trajectory::new(2, 1, obs, vec![0.0; t], vec![0.0; t], vec![false; t], vec![false; t])
            .unwrap()
    }

    #[test]
    fn population_std_plus_epsilon_and_duplicates_count_twice() {
        let a = TaskDataset::new(vec![traj(vec![0.0, 10.0, 2.0, 10.0])]).unwrap();
        let b = TaskDataset::new(vec![traj(vec![4.0, 10.0])]).unwrap();
        let n = StateNorm::from_datasets(2, [&a, &b]);
        assert_eq!(n.mean, vec![2.0, 10.0]);
        // population std of {0, 2, 4} = sqrt(8/3)
        assert!((n.std[0] - ((8.0f64 / 3.0).sqrt() as f32 + 1e-6)).abs() < 1e-7);
        assert_eq!(n.std[1], 1e-6); // constant dimension: std 0 + 1e-6
                                    // the same dataset passed twice weighs twice (reference: train list + test list)
        let n2 = StateNorm::from_datasets(2, [&a, &a, &b]);
        assert!((n2.mean[0] - 1.6).abs() < 1e-6);
        assert_eq!(n.apply(0, 2.0), 0.0);
    }
}
