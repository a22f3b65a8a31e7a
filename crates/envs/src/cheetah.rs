//! HalfCheetah-Dir (`cheetah_dir`) and HalfCheetah-Vel (`cheetah_vel`), as the reference defines
//! them (`promptdt-reference.md` e.1, e.2; `tp_envs/half_cheetah_{dir,vel}.py` of PEARL/MACAW/
//! Prompt-DT): gym's `half_cheetah.xml`, frame skip 5 (dt 0.05 s), 200-step episodes that never
//! terminate.
//!
//! - Observation (20, f32): `qpos[1:9]` ‖ `qvel[0:9]` ‖ `xpos(torso)` as `mj_step` leaves it (one
//!   0.01 s sub-step stale, see [`crate::mujoco_env`]); index 17 is the (stale) absolute x position.
//! - Action (6): motor commands in [-1, 1] (MuJoCo clamps; the reward uses the raw action).
//! - Reward, with `x = qpos[0]` (fresh) before and after the step and `v = (x_after - x_before)/dt`:
//!   Dir: `direction * v - 0.05 ||a||^2`; Vel: `-|v - v_goal| - 0.05 ||a||^2`.

use crate::mujoco_env::{action_sq_norm, Body, MujocoEnv, MujocoTask, StepState, HORIZON};
use crate::replay::{replay_mujoco_init, ReplayResult};
use crate::{numeric_param, ActionBounds, DatasetBar, Env, EnvError, EnvFamily, EnvPreset};

/// Family names, as used in file names (`cheetah_vel-3-prompt-expert.pkl`).
pub const DIR_ENV_NAME: &str = "cheetah_dir";
pub const VEL_ENV_NAME: &str = "cheetah_vel";

/// Weight of `||a||^2` in both rewards (`0.5 * 1e-1` in the reference).
pub const CTRL_COST_WEIGHT: f64 = 0.05;

/// Task directions of HalfCheetah-Dir: task 0 runs forward, task 1 backward.
///
/// Provenance: the reference's `config/cheetah_dir/config_cheetah_dir_task{0,1}.pkl` =
/// `[{'direction': 1}]`, `[{'direction': -1}]` (`../shared/data/official-task-parameters.json`,
/// key `cheetah_dir_direction`).
pub const DIRECTIONS: [f64; 2] = [1.0, -1.0];

/// Number of HalfCheetah-Vel tasks.
pub const NUM_VEL_TASKS: usize = 40;

/// Target velocities of HalfCheetah-Vel, m/s: `numpy.linspace(0.075, 3.0, 40)`, i.e. about
/// 0.075 (i + 1).
///
/// Provenance: the reference's `config/cheetah_vel/config_cheetah_vel_task{i}.pkl` =
/// `[{'velocity': v_i}]`; these are the f64 values of
/// `../shared/data/official-task-parameters.json` (key `cheetah_vel_target_velocity`), written out
/// with all their digits so that they are numpy's values bit for bit (a test checks the file).
pub const VELOCITIES: [f64; NUM_VEL_TASKS] = [
    0.075,
    0.15,
    0.22499999999999998,
    0.3,
    0.375,
    0.45,
    0.5249999999999999,
    0.6,
    0.6749999999999999,
    0.7499999999999999,
    0.825,
    0.8999999999999999,
    0.9749999999999999,
    1.05,
    1.125,
    1.2,
    1.275,
    1.3499999999999999,
    1.4249999999999998,
    1.5,
    1.575,
    1.65,
    1.7249999999999999,
    1.7999999999999998,
    1.8749999999999998,
    1.95,
    2.025,
    2.1,
    2.1750000000000003,
    2.25,
    2.325,
    2.4,
    2.475,
    2.5500000000000003,
    2.625,
    2.7,
    2.775,
    2.85,
    2.9250000000000003,
    3.0,
];

/// Test tasks of cheetah_vel's `default` split (the reference's `cheetah_vel_40.json`, = MACAW's).
pub const VEL_DEFAULT_TEST_TASKS: [usize; 5] = [2, 7, 15, 23, 26];

/// HalfCheetah-Dir reward: `direction * (x_after - x_before)/dt - 0.05 ||a||^2`, x = `qpos[0]`.
pub fn dir_reward(direction: f64, x_before: f64, x_after: f64, dt: f64, action: &[f32]) -> f64 {
    let forward_vel = (x_after - x_before) / dt;
    direction * forward_vel - CTRL_COST_WEIGHT * action_sq_norm(action)
}

/// HalfCheetah-Vel reward: `-|(x_after - x_before)/dt - velocity| - 0.05 ||a||^2`, x = `qpos[0]`.
pub fn vel_reward(velocity: f64, x_before: f64, x_after: f64, dt: f64, action: &[f32]) -> f64 {
    let forward_vel = (x_after - x_before) / dt;
    -(forward_vel - velocity).abs() - CTRL_COST_WEIGHT * action_sq_norm(action)
}

/// A HalfCheetah-Dir task: run in direction `direction` (+1 forward, -1 backward).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheetahDirTask {
    pub direction: f64,
}

impl MujocoTask for CheetahDirTask {
    fn body(&self) -> Body {
        Body::HalfCheetah
    }

    fn env_name(&self) -> &'static str {
        DIR_ENV_NAME
    }

    fn reward(&self, s: &mut StepState<'_>, action: &[f32]) -> (f64, bool) {
        (dir_reward(self.direction, s.x_before, s.x_after, s.dt, action), false)
    }
}

/// A HalfCheetah-Vel task: run forward at `velocity` m/s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheetahVelTask {
    pub velocity: f64,
}

impl MujocoTask for CheetahVelTask {
    fn body(&self) -> Body {
        Body::HalfCheetah
    }

    fn env_name(&self) -> &'static str {
        VEL_ENV_NAME
    }

    fn reward(&self, s: &mut StepState<'_>, action: &[f32]) -> (f64, bool) {
        (vel_reward(self.velocity, s.x_before, s.x_after, s.dt, action), false)
    }
}

/// Recovers the fresh root x position from a recorded cheetah observation: `obs[17]` is the torso
/// x one sub-step (h = 0.01 s) before the step ended, and semi-implicit Euler moved it by
/// `h * qvel[0] = 0.01 * obs[8]` since. `first` marks the reset observation, where `xpos` is fresh.
pub fn root_x_from_obs(obs: &[f32], first: bool) -> f64 {
    let stale = f64::from(obs[17]);
    if first {
        stale
    } else {
        stale + 0.01 * f64::from(obs[8])
    }
}

/// HalfCheetah-Dir: 2 tasks (forward, backward). Build it with `default()`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CheetahDirFamily {
    _private: (),
}

impl CheetahDirFamily {
    /// The environment of `task`, as a concrete type (for state access and replay).
    pub fn make_env(&self, task: usize) -> Result<MujocoEnv, EnvError> {
        EnvError::check_task(DIR_ENV_NAME, task, DIRECTIONS.len())?;
        MujocoEnv::new(Box::new(CheetahDirTask { direction: DIRECTIONS[task] }))
    }
}

impl EnvFamily for CheetahDirFamily {
    fn name(&self) -> &str {
        DIR_ENV_NAME
    }

    fn num_tasks(&self) -> usize {
        DIRECTIONS.len()
    }

    /// `promptdt-reference.md` c.4. G* is the code's 1500; the paper's Table 3 says 1000.
    fn preset(&self) -> EnvPreset {
        EnvPreset {
            obs_dim: Body::HalfCheetah.obs_dim(),
            act_dim: Body::HalfCheetah.act_dim(),
            horizon: HORIZON,
            rtg_scale: 1000.0,
            target_return: 1500.0,
            prompt_length: 5,
        }
    }

    fn split_names(&self) -> Vec<String> {
        vec!["default".into()]
    }

    /// `default`: train [0, 1], test [0, 1] — the same tasks, as in the reference
    /// (`config/cheetah_dir/cheetah_dir_2.json`).
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        match name {
            "default" => Ok((vec![0, 1], vec![0, 1])),
            other => Err(EnvError::unknown_split(DIR_ENV_NAME, other, &["default"])),
        }
    }

    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        EnvError::check_task(DIR_ENV_NAME, task, DIRECTIONS.len())?;
        Ok(serde_json::json!({ "direction": DIRECTIONS[task] }))
    }

    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(self.make_env(task)?))
    }

    /// MuJoCo clamps the controls to [-1, 1].
    /// Frame skip 5 x MuJoCo timestep 0.01 s (gymnasium's HalfCheetah: 20).
    fn render_fps(&self) -> u32 {
        20
    }

    fn action_bounds(&self) -> ActionBounds {
        ActionBounds::symmetric(1.0, self.preset().act_dim)
    }

    fn rl_preset(&self) -> Option<&'static str> {
        Some(include_str!("../../../configs/collect/cheetah_dir.toml"))
    }

    /// `[direction]`.
    fn task_features(&self, task: usize) -> Result<Vec<f32>, EnvError> {
        Ok(vec![numeric_param(DIR_ENV_NAME, task, &self.task_params(task)?, "direction")?])
    }

    fn dataset_bar(&self) -> Option<DatasetBar> {
        Some(DatasetBar::Reference {
            tolerance: 0.10,
            name: "expert ≥ 90 % of the reference's return on every task",
        })
    }

    fn replay(
        &self,
        task: usize,
        init: Option<&str>,
        actions: &[Vec<f32>],
    ) -> Result<ReplayResult, EnvError> {
        replay_mujoco_init(&mut self.make_env(task)?, self.name(), task, init, actions)
    }
}

/// HalfCheetah-Vel: 40 target velocities. Build it with `default()`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CheetahVelFamily {
    _private: (),
}

impl CheetahVelFamily {
    /// The environment of `task`, as a concrete type (for state access and replay).
    pub fn make_env(&self, task: usize) -> Result<MujocoEnv, EnvError> {
        EnvError::check_task(VEL_ENV_NAME, task, NUM_VEL_TASKS)?;
        MujocoEnv::new(Box::new(CheetahVelTask { velocity: VELOCITIES[task] }))
    }
}

impl EnvFamily for CheetahVelFamily {
    fn name(&self) -> &str {
        VEL_ENV_NAME
    }

    fn num_tasks(&self) -> usize {
        NUM_VEL_TASKS
    }

    /// `promptdt-reference.md` c.4: returns are negative, G* = 0 asks for the best behaviour.
    fn preset(&self) -> EnvPreset {
        EnvPreset {
            obs_dim: Body::HalfCheetah.obs_dim(),
            act_dim: Body::HalfCheetah.act_dim(),
            horizon: HORIZON,
            rtg_scale: 500.0,
            target_return: 0.0,
            prompt_length: 5,
        }
    }

    fn split_names(&self) -> Vec<String> {
        vec!["default".into()]
    }

    /// `default`: test [2, 7, 15, 23, 26], train the other 35 (`cheetah_vel_40.json`).
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        match name {
            "default" => {
                let test = VEL_DEFAULT_TEST_TASKS.to_vec();
                let train = (0..NUM_VEL_TASKS).filter(|t| !test.contains(t)).collect();
                Ok((train, test))
            }
            other => Err(EnvError::unknown_split(VEL_ENV_NAME, other, &["default"])),
        }
    }

    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        EnvError::check_task(VEL_ENV_NAME, task, NUM_VEL_TASKS)?;
        Ok(serde_json::json!({ "velocity": VELOCITIES[task] }))
    }

    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(self.make_env(task)?))
    }

    /// MuJoCo clamps the controls to [-1, 1].
    /// Frame skip 5 x MuJoCo timestep 0.01 s (gymnasium's HalfCheetah: 20).
    fn render_fps(&self) -> u32 {
        20
    }

    fn action_bounds(&self) -> ActionBounds {
        ActionBounds::symmetric(1.0, self.preset().act_dim)
    }

    fn rl_preset(&self) -> Option<&'static str> {
        Some(include_str!("../../../configs/collect/cheetah_vel.toml"))
    }

    /// `[velocity]`.
    fn task_features(&self, task: usize) -> Result<Vec<f32>, EnvError> {
        Ok(vec![numeric_param(VEL_ENV_NAME, task, &self.task_params(task)?, "velocity")?])
    }

    fn dataset_bar(&self) -> Option<DatasetBar> {
        Some(DatasetBar::Reference {
            tolerance: 0.15,
            name: "expert within 15 % of the reference's return (or better) on every task",
        })
    }

    fn replay(
        &self,
        task: usize,
        init: Option<&str>,
        actions: &[Vec<f32>],
    ) -> Result<ReplayResult, EnvError> {
        replay_mujoco_init(&mut self.make_env(task)?, self.name(), task, init, actions)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn velocities_are_numpy_linspace() {
        // numpy: start + i * step for i < n - 1, the last point exactly `stop`.
        let step = (3.0 - 0.075) / 39.0;
        for (i, &v) in VELOCITIES.iter().enumerate().take(39) {
            assert_eq!(v, 0.075 + i as f64 * step, "task {i}");
        }
        assert_eq!(VELOCITIES[39], 3.0);
    }

    #[test]
    fn rewards_follow_the_formulas() {
        let a = [0.5f32, -0.5, 1.0, 0.0, 0.0, -1.0];
        // ||a||^2 = 2.5, control cost 0.125; v = (1.1 - 1.0) / 0.05 = 2.
        let d = dir_reward(1.0, 1.0, 1.1, 0.05, &a);
        assert!((d - (2.0 - 0.125)).abs() < 1e-12, "{d}");
        let b = dir_reward(-1.0, 1.0, 1.1, 0.05, &a);
        assert!((b - (-2.0 - 0.125)).abs() < 1e-12, "{b}");
        let v = vel_reward(1.5, 1.0, 1.1, 0.05, &a);
        assert!((v - (-0.5 - 0.125)).abs() < 1e-12, "{v}");
        assert_eq!(vel_reward(2.0, 0.0, 0.1, 0.05, &[0.0; 6]), 0.0);
    }

    #[test]
    fn splits_and_presets() {
        let vel = CheetahVelFamily::default();
        let (train, test) = vel.split("default").unwrap_or_default();
        assert_eq!(test, vec![2, 7, 15, 23, 26]);
        assert_eq!(train.len(), 35);
        assert!(train.iter().all(|t| !test.contains(t)));
        assert_eq!(vel.preset().rtg_scale, 500.0);
        let dir = CheetahDirFamily::default();
        assert_eq!(dir.split("default"), Ok((vec![0, 1], vec![0, 1])));
        assert_eq!(dir.preset().target_return, 1500.0);
        assert_eq!(dir.preset().rtg_scale, 1000.0);
        assert!(matches!(dir.split("ood"), Err(EnvError::UnknownSplit { .. })));
        assert!(matches!(vel.task_params(40), Err(EnvError::UnknownTask { task: 40, n: 40, .. })));
    }
}
