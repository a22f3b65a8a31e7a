//! Checks the cheetah reward functions against data nobody on this project wrote: the reference
//! release's 42 prompt files (`official-prompts/`, recorded with the reference environments on
//! MuJoCo 2.0; found by `pdt_testkit::reference`, and skipped without them except in CI). For every transition the reward is recomputed from the recorded
//! observations and action with the same functions the environments call
//! (`cheetah::{dir_reward, vel_reward}`), and compared with the recorded reward.
//!
//! The observation holds the torso x one sub-step stale (`docs/mujoco-envs.md`), so the fresh root
//! x is recovered as `obs[17] + 0.01 * obs[8]` (`cheetah::root_x_from_obs`); at t = 0 (right after
//! reset) `obs[17]` is exact. The remaining error is float32 rounding of x (up to 60 m) and of the
//! recorded reward: measured 7.1e-5 (cheetah_dir, 2,000 transitions) and 3.7e-5 (cheetah_vel,
//! 40,000 transitions); with plain `obs[17]` differences it would be 0.59 and 0.63.

use std::path::{Path, PathBuf};

use pdt_data::pickle::{self, PyValue};
use pdt_data::reference::{load_pickle, ReferenceOptions};
use pdt_envs::cheetah::{self, DIRECTIONS, VELOCITIES};

/// Bound on |recomputed - recorded| over all transitions (see the module docs for the measured max).
const TOLERANCE: f64 = 1e-4;
/// With plain `obs[17]` differences (ignoring the stale torso position) the error is far larger.
const STALE_ERROR_AT_LEAST: f64 = 0.1;
const DT: f64 = 0.05;

/// `next_observations[-1]` of each trajectory: the observation after the last step, which
/// `load_pickle` drops (the reference never reads `next_observations`).
fn last_next_observations(path: &Path) -> Vec<Vec<f32>> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let root = pickle::parse(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let PyValue::List(trajs) = root else { panic!("{}: not a list", path.display()) };
    trajs
        .iter()
        .map(|t| match t.get("next_observations") {
            Some(PyValue::NdArray(a)) => {
                let v = a
                    .to_c_order()
                    .to_f32_vec()
                    .unwrap_or_else(|| panic!("next_observations dtype"));
                v[v.len() - 20..].to_vec()
            }
            _ => panic!("{}: no next_observations", path.display()),
        })
        .collect()
}

struct Errors {
    max: f64,
    max_stale: f64,
    transitions: usize,
}

/// Recomputes every reward of one file; `reward(x_before, x_after, action)`.
fn check_file(path: &Path, reward: &dyn Fn(f64, f64, &[f32]) -> f64, errors: &mut Errors) {
    let loaded = load_pickle(path, &ReferenceOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    let ds = loaded.dataset;
    assert_eq!((ds.obs_dim, ds.act_dim), (20, 6), "{}", path.display());
    let lasts = last_next_observations(path);
    for (traj, last) in ds.trajectories.iter().zip(&lasts) {
        let n = traj.rewards.len();
        let obs = |t: usize| -> &[f32] {
            if t < n {
                &traj.observations[t * 20..(t + 1) * 20]
            } else {
                last
            }
        };
        for t in 0..n {
            let action = &traj.actions[t * 6..(t + 1) * 6];
            let x0 = cheetah::root_x_from_obs(obs(t), t == 0);
            let x1 = cheetah::root_x_from_obs(obs(t + 1), false);
            let recorded = f64::from(traj.rewards[t]);
            let err = (reward(x0, x1, action) - recorded).abs();
            errors.max = errors.max.max(err);
            let stale = reward(f64::from(obs(t)[17]), f64::from(obs(t + 1)[17]), action);
            errors.max_stale = errors.max_stale.max((stale - recorded).abs());
            errors.transitions += 1;
        }
    }
}

fn file(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}-prompt-expert.pkl"))
}

#[test]
fn cheetah_dir_rewards_match_the_reference_data() {
    let Some(dir) = pdt_testkit::reference::official_prompts() else { return };
    let mut errors = Errors { max: 0.0, max_stale: 0.0, transitions: 0 };
    for (task, &direction) in DIRECTIONS.iter().enumerate() {
        let reward =
            move |x0: f64, x1: f64, a: &[f32]| cheetah::dir_reward(direction, x0, x1, DT, a);
        check_file(&file(&dir, &format!("cheetah_dir-{task}")), &reward, &mut errors);
    }
    eprintln!(
        "cheetah_dir: {} transitions, max |error| {:.3e} (plain obs[17]: {:.3e})",
        errors.transitions, errors.max, errors.max_stale
    );
    assert_eq!(errors.transitions, 2 * 5 * 200);
    assert!(errors.max < TOLERANCE, "max error {}", errors.max);
    assert!(errors.max_stale > STALE_ERROR_AT_LEAST, "stale-xpos error only {}", errors.max_stale);
}

#[test]
fn cheetah_vel_rewards_match_the_reference_data() {
    let Some(dir) = pdt_testkit::reference::official_prompts() else { return };
    let mut errors = Errors { max: 0.0, max_stale: 0.0, transitions: 0 };
    for (task, &velocity) in VELOCITIES.iter().enumerate() {
        let reward =
            move |x0: f64, x1: f64, a: &[f32]| cheetah::vel_reward(velocity, x0, x1, DT, a);
        check_file(&file(&dir, &format!("cheetah_vel-{task}")), &reward, &mut errors);
    }
    eprintln!(
        "cheetah_vel: {} transitions, max |error| {:.3e} (plain obs[17]: {:.3e})",
        errors.transitions, errors.max, errors.max_stale
    );
    assert_eq!(errors.transitions, 40 * 5 * 200);
    assert!(errors.max < TOLERANCE, "max error {}", errors.max);
    assert!(errors.max_stale > STALE_ERROR_AT_LEAST, "stale-xpos error only {}", errors.max_stale);
}

#[test]
fn task_parameters_match_the_official_file() {
    let Some(path) = pdt_testkit::reference::task_parameters() else { return };
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let json: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}"));
    let floats = |key: &str| -> Vec<f64> {
        json[key]
            .as_array()
            .unwrap_or_else(|| panic!("{key}"))
            .iter()
            .filter_map(|v| v.as_f64())
            .collect()
    };
    assert_eq!(floats("cheetah_dir_direction"), DIRECTIONS.to_vec());
    assert_eq!(floats("cheetah_vel_target_velocity"), VELOCITIES.to_vec());
    assert_eq!(floats("ant_dir_goal_radians"), pdt_envs::ant_dir::GOALS.to_vec());
}
