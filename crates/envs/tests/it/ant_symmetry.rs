//! The Ant's mirror symmetries (`ant_dir::Symmetry`): a mirrored state stepped with mirrored
//! actions stays the mirror of the original trajectory, with the same rewards for the mirrored
//! goal.
#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use pdt_envs::ant_dir::AntDirTask;
use pdt_envs::ant_dir::{ContactCost, Symmetry, GOALS};
use pdt_envs::mujoco_env::MujocoEnv;
use pdt_envs::Env;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn ant(goal: f64) -> MujocoEnv {
    MujocoEnv::new(Box::new(AntDirTask { goal, contact_cost: ContactCost::default() })).unwrap()
}

#[test]
fn symmetries_are_involutions_of_the_right_sizes() {
    for r in Symmetry::ALL {
        for (p, n) in [(r.qpos(), 15), (r.qvel(), 14), (r.observation(), 27), (r.action(), 8)] {
            assert_eq!((p.index.len(), p.sign.len()), (n, n));
            let x: Vec<f64> = (0..n).map(|i| i as f64 + 1.0).collect();
            assert_eq!(p.apply(&p.apply(&x)), x, "{}", r.name());
            let mut seen = p.index.clone();
            seen.sort_unstable();
            assert_eq!(seen, (0..n).collect::<Vec<_>>(), "a permutation");
        }
        for g in GOALS {
            let m = r.goal(g);
            let s = r.direction_signs();
            assert!(
                (m.cos() - s[0] * g.cos()).abs() < 1e-12
                    && (m.sin() - s[1] * g.sin()).abs() < 1e-12
            );
        }
    }
}

#[test]
fn a_mirrored_trajectory_is_a_trajectory_of_the_mirrored_goal() {
    for r in Symmetry::ALL {
        for (k, &g) in GOALS.iter().take(3).enumerate() {
            let (mut a, mut b) = (ant(g), ant(r.goal(g)));
            let obs_a = a.reset(k as u64 + 11);
            let (q, v) = (r.qpos().apply(a.qpos()), r.qvel().apply(a.qvel()));
            let obs_b = b.reset_to(&q, &v).unwrap();
            let mirror_obs = r.observation();
            let close = |x: &[f32], y: &[f64], tol: f64, what: &str| {
                for (i, (&p, &q)) in x.iter().zip(y).enumerate() {
                    assert!(
                        (p as f64 - q).abs() <= tol,
                        "{} step {what}: obs[{i}] {p} vs {q}",
                        r.name()
                    );
                }
            };
            close(&obs_b, &mirror_obs.apply(&obs_a), 1e-6, "reset");
            let mut rng = ChaCha8Rng::seed_from_u64(k as u64);
            let (mut ret_a, mut ret_b) = (0.0, 0.0);
            for t in 0..100 {
                let act: Vec<f32> = (0..8).map(|_| rng.random_range(-1.0f32..=1.0)).collect();
                let act_b: Vec<f32> = r.action().apply(&act).iter().map(|&x| x as f32).collect();
                let (sa, sb) = (a.step(&act).unwrap(), b.step(&act_b).unwrap());
                // Contacts make the dynamics chaotic; the mirror holds to float rounding for a while.
                let tol = if t < 30 { 1e-3 } else { f64::INFINITY };
                close(&sb.obs, &mirror_obs.apply(&sa.obs), tol, &t.to_string());
                if t < 30 {
                    assert!(
                        (sa.reward - sb.reward).abs() < 1e-3,
                        "{} reward at {t}: {} vs {}",
                        r.name(),
                        sa.reward,
                        sb.reward
                    );
                }
                ret_a += sa.reward as f64;
                ret_b += sb.reward as f64;
                if sa.terminated || sb.terminated {
                    break;
                }
            }
            assert!(ret_a.is_finite() && ret_b.is_finite());
        }
    }
}
