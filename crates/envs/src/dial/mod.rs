//! Dial (`dial`): the paper's fifth benchmark (sec. 5.1, "control a 6-DOF Jaco robot to reach a
//! target number located in a number pad"), **reconstructed** on MuJoCo 3.17. The original scene
//! (TACO's Jaco pin-pad) is GPL-3.0 and none of it is used: `assets/dial/dial.xml` is our own
//! scene, written by `scripts/dial/build_scene.py` from dm_control's Kinova Jaco numbers
//! (BSD-3-Clause, `assets/dial/NOTICE`) and the pin-pad facts of `shared/reference/dial.md`
//! (cited as "spec §n"); `assets/dial/targets.json` holds the hover/press/init joint poses our own
//! inverse kinematics computed for it (`scripts/dial/twin.py targets`). `docs/dial.md` says what
//! was kept from the original and what differs.
//!
//! - Task: a digit 0..9 (not observed); the paper's split trains on 1, 2, 3, 4, 5, 8 and tests on
//!   6, 7, 9, 0.
//! - Action (9, f32): torques for the 6 arm and 3 finger motors (gears 50, 100, 100, 50, 50, 50, 10,
//!   10, 10), clipped to the original's box [`C_LOW`, `C_HIGH`] and held for 20 sub-steps of 2 ms
//!   (25 Hz).
//! - Observation (39): the 9 joint angles (unwrapped), then for each digit k = 0..9 the offset
//!   `ee - press_xyz[k]`, where `ee` is the finger-3 proximal body origin (the original's end
//!   effector, `body_xpos[-1]`) as `mj_step` leaves it (the positions at the start of the last
//!   sub-step, as mujoco-py's `sim.step` left them to the original).
//! - Reward: 1 on the sub-step where `|ee - press_xyz[digit]|_1 < 0.1`, which ends the episode
//!   (terminated); 0 otherwise. Truncated after [`HORIZON`] steps.
//! - Reset: the init pose at rest, one sub-step, the PI controller's correction, one more sub-step
//!   (the original's `move_to_position` + `update`). Deterministic; [`Dial::reset_from`] starts
//!   from a perturbed pose and lets the controller settle back first (data collection, as the
//!   original's collector did).
//!
//! `scripts/dial/twin.py` is a Python twin on the `mujoco` bindings; `tests/it/dial_parity.rs`
//! replays its fixtures and requires bit-equal observations, rewards and flags.
//!
//! Its datasets are collected by the scripted policies of `collect.rs` (`DialPolicies`:
//! the PI controller with DART noise), on the machinery every scripted family shares
//! (`collect_scripted`).

use std::sync::{Arc, OnceLock};

use mujoco_rs::prelude::{MjData, MjModel, MjtObjBase};
use mujoco_rs::wrappers::MjVfs;
use rand::Rng;
use serde::Deserialize;

use crate::collect_scripted::ScriptedFamily;
use crate::replay::ReplayResult;
use crate::{ActionBounds, Env, EnvError, EnvFamily, EnvPreset, StepResult};

// The scripted policies that collect Dial's datasets (the machinery: `collect_scripted`).
mod collect;
pub use collect::{run_dial_episode, DIAL_DART_AMOUNTS, DIAL_MEDIUM_TARGET_NOISE};

/// Family name, as used in file names.
pub const ENV_NAME: &str = "dial";
pub const OBS_DIM: usize = 39;
pub const ACT_DIM: usize = 9;
/// Number of joints (6 arm + 3 fingers); `nq = nv = nu`.
pub const NQ: usize = 9;
/// Time limit: `jacopinpad_multi._max_episode_steps` (spec §2.5; the original env's own cap of 300
/// steps never binds before it).
pub const HORIZON: usize = 200;
/// Sub-steps per environment step (2 ms each: 25 Hz control).
pub const ACTION_REPEAT: usize = 20;
/// The success radius: L1 distance (m) between the end effector and the digit's press point.
pub const SUCCESS_L1: f64 = 0.1;
/// The reward of the step that reaches the digit (and of no other step).
pub const SUCCESS_REWARD: f32 = 1.0;
pub const NUM_TASKS: usize = 10;
/// The paper's split (sec. 6.1): train on 6 digits, test on 4.
pub const TRAIN_TASKS: [usize; 6] = [1, 2, 3, 4, 5, 8];
pub const TEST_TASKS: [usize; 4] = [6, 7, 9, 0];
/// The original's action box (spec §2.4), in our joint convention (joints 1 and 2 turn about -z
/// so that its signs carry over: a negative joint-2 torque lifts the arm).
pub const C_HIGH: [f64; ACT_DIM] = [0.07, 0.6, 0.07, 0.05, 0.07, 0.065, 0.07, 0.07, 0.07];
pub const C_LOW: [f64; ACT_DIM] = [-0.07, -1.0, -0.134, -0.05, -0.07, -0.065, -0.07, -0.07, -0.07];
/// The original PI controller's gains (spec §3.1), computed as it computes them (`8.5 * [...]`,
/// `0.1 * [...]`) so that the products round the same way.
pub const KP: [f64; NQ] = [
    8.5 * 0.5,
    8.5 * 2.5,
    8.5 * 0.9,
    8.5 * 0.9,
    8.5 * 0.9,
    8.5 * 1.0,
    8.5 * 1.0,
    8.5 * 1.0,
    8.5 * 1.0,
];
pub const KI: [f64; NQ] = [
    0.1 * 0.001,
    0.1 * 0.001,
    0.1 * 0.001,
    0.1 * 0.005,
    0.1 * 0.005,
    0.1 * 0.001,
    0.1 * 0.001,
    0.1 * 0.001,
    0.1 * 0.001,
];
/// Error vectors the PI controller's integral sums over.
pub const PI_MEMORY: usize = 200;
/// Reset settles when the L1 joint error to the init pose is below this (rad), or after
/// [`SETTLE_MAX`] sub-steps.
pub const SETTLE_TOL: f64 = 0.03;
pub const SETTLE_MAX: usize = 1000;
/// Start-state noise of data collection (the original collector's, spec §3.2): every joint
/// `+ U(-0.1, 0.1)`, then joint 1 `+ U(0, 0.2)` and joint 2 `+ U(-0.2, 0)`.
pub const START_NOISE: f64 = 0.1;

/// Return-to-go divisor. Returns are 0 or 1, so no scaling (our choice: the paper gives none).
pub const RTG_SCALE: f32 = 1.0;
/// G*: the best return, 1. The paper's Table 3 says 10 for Dial against returns of at most 1
/// (spec §2.5, an open question); 10 stays one setting away (`eval.target_return = 10`).
pub const TARGET_RETURN: f32 = 1.0;
/// Prompt length K* of the paper's Table 3.
pub const PROMPT_LENGTH: usize = 15;

const SCENE: &str = "dial.xml";
const SCENE_XML: &[u8] = include_bytes!("../../assets/dial/dial.xml");
const TARGETS_JSON: &str = include_str!("../../assets/dial/targets.json");

fn sim_error(message: String) -> EnvError {
    EnvError::Simulation { env: ENV_NAME.into(), message }
}

/// The joint poses of `assets/dial/targets.json` (our inverse kinematics; `docs/dial.md`).
#[derive(Debug, Clone, Deserialize)]
pub struct Targets {
    /// Per digit: the pose the expert drives to (hand 4 cm above the key).
    pub hover: Vec<[f64; NQ]>,
    /// Per digit: the pose 1.5 cm above the key that defines the press point.
    pub press: Vec<[f64; NQ]>,
    /// Per digit: the end effector's position at the press pose (the reward's target).
    pub press_xyz: Vec<[f64; 3]>,
    /// The start pose.
    pub init: [f64; NQ],
}

/// The targets, parsed once.
pub fn targets() -> Result<&'static Targets, EnvError> {
    static TARGETS: OnceLock<Result<Targets, String>> = OnceLock::new();
    TARGETS
        .get_or_init(|| {
            let t: Targets = serde_json::from_str(TARGETS_JSON).map_err(|e| e.to_string())?;
            if t.hover.len() != NUM_TASKS
                || t.press.len() != NUM_TASKS
                || t.press_xyz.len() != NUM_TASKS
            {
                return Err(format!("expected {NUM_TASKS} digits"));
            }
            Ok(t)
        })
        .as_ref()
        .map_err(|m| sim_error(format!("assets/dial/targets.json: {m}")))
}

/// The compiled scene, loaded once per process and shared (read-only) by every environment.
fn load_model() -> Result<Arc<MjModel>, EnvError> {
    static MODEL: OnceLock<Result<Arc<MjModel>, String>> = OnceLock::new();
    crate::mujoco_env::init_logging();
    let loaded = MODEL.get_or_init(|| {
        let mut vfs = MjVfs::new();
        vfs.add_from_buffer(SCENE, SCENE_XML).map_err(|e| format!("{SCENE}: {e:?}"))?;
        let model = MjModel::from_xml_vfs(SCENE, &vfs).map_err(|e| format!("{e:?}"))?;
        let m = model.ffi();
        if (m.nq, m.nv, m.nu) != (NQ as i64, NQ as i64, ACT_DIM as i64) {
            return Err(format!("expected nq = nv = nu = {NQ}, got {} {} {}", m.nq, m.nv, m.nu));
        }
        Ok(Arc::new(model))
    });
    loaded.clone().map_err(|m| sim_error(format!("cannot load the Dial scene: {m}")))
}

/// `x` wrapped to [-pi, pi) as the original computes it (`(x + pi) % (2 pi) - pi`, Python's
/// floored modulo), through C's `fmod` as the twin does.
pub fn wrap(x: f64) -> f64 {
    use std::f64::consts::PI;
    let two_pi = 2.0 * PI;
    ((x + PI) % two_pi + two_pi) % two_pi - PI
}

/// Clips to the action box, per joint.
pub fn clip_box(a: [f64; ACT_DIM]) -> [f64; ACT_DIM] {
    std::array::from_fn(|j| a[j].max(C_LOW[j]).min(C_HIGH[j]))
}

/// The original's joint-space PI controller (spec §3.1): `a = KP * e + KI * S`, `e` the wrapped
/// joint error and `S` the scalar sum of every entry of the last <= 200 error vectors before this
/// one (summed oldest first, entry by entry), clipped to the action box.
///
/// Deliberate difference: the original kept one controller (and its memory) across resets; here
/// each reset and each expert episode starts with an empty memory, so an episode does not depend
/// on the ones before it.
#[derive(Debug, Clone, Default)]
pub struct PiController {
    memory: std::collections::VecDeque<[f64; NQ]>,
}

impl PiController {
    pub fn act(&mut self, q: &[f64; NQ], target: &[f64; NQ]) -> [f64; ACT_DIM] {
        let e: [f64; NQ] = std::array::from_fn(|j| wrap(target[j] - q[j]));
        let mut s = 0.0;
        for v in &self.memory {
            for x in v {
                s += x;
            }
        }
        let a = std::array::from_fn(|j| KP[j] * e[j] + KI[j] * s);
        self.memory.push_back(e);
        if self.memory.len() > PI_MEMORY {
            self.memory.pop_front();
        }
        clip_box(a)
    }
}

/// One Dial step at full precision.
#[derive(Debug, Clone, PartialEq)]
pub struct DialStep {
    pub obs: [f64; OBS_DIM],
    pub reward: f64,
    /// The target digit was reached (the episode ends: terminated).
    pub success: bool,
    pub truncated: bool,
}

/// One Dial task (see the module docs).
#[derive(Debug)]
pub struct Dial {
    data: MjData<Arc<MjModel>>,
    ee: usize,
    digit: usize,
    targets: &'static Targets,
    obs: [f64; OBS_DIM],
    t: usize,
    finished: bool,
}

impl Dial {
    /// The task of `digit` (0..9), already reset.
    pub fn new(digit: usize) -> Result<Self, EnvError> {
        if digit >= NUM_TASKS {
            return Err(EnvError::UnknownTask { env: ENV_NAME.into(), task: digit, n: NUM_TASKS });
        }
        let model = load_model()?;
        let ee = model
            .name_to_id(MjtObjBase::mjOBJ_BODY, "b_finger_3")
            .ok_or_else(|| sim_error("the scene has no b_finger_3".into()))?;
        let data = MjData::try_new(model)
            .map_err(|e| sim_error(format!("cannot allocate mjData: {e:?}")))?;
        let mut env = Self {
            data,
            ee,
            digit,
            targets: targets()?,
            obs: [0.0; OBS_DIM],
            t: 0,
            finished: false,
        };
        env.reset_f64();
        Ok(env)
    }

    pub fn digit(&self) -> usize {
        self.digit
    }

    /// The latest observation at full precision.
    pub fn obs_f64(&self) -> &[f64; OBS_DIM] {
        &self.obs
    }

    /// Steps taken in the current episode.
    pub fn steps(&self) -> usize {
        self.t
    }

    /// The joint angles (qpos).
    pub fn qpos(&self) -> [f64; NQ] {
        std::array::from_fn(|j| self.data.qpos()[j])
    }

    /// The end effector's position (finger-3 proximal body origin, as the last `mj_step` left it).
    pub fn ee(&self) -> [f64; 3] {
        self.data.xpos()[self.ee]
    }

    /// L1 distance from the end effector to the target digit's press point.
    pub fn distance(&self) -> f64 {
        let p = self.ee();
        let g = self.targets.press_xyz[self.digit];
        (g[0] - p[0]).abs() + (g[1] - p[1]).abs() + (g[2] - p[2]).abs()
    }

    fn observation(&self) -> [f64; OBS_DIM] {
        let mut obs = [0.0; OBS_DIM];
        obs[..NQ].copy_from_slice(&self.qpos());
        let p = self.ee();
        for (k, g) in self.targets.press_xyz.iter().enumerate() {
            for i in 0..3 {
                obs[NQ + 3 * k + i] = p[i] - g[i];
            }
        }
        obs
    }

    /// The deterministic reset (the init pose; see the module docs).
    pub fn reset_f64(&mut self) -> [f64; OBS_DIM] {
        let init = self.targets.init;
        self.start(&init)
    }

    /// Starts from `qpos` (at rest) and lets the PI controller bring the arm back to the init pose
    /// (until the L1 joint error is below [`SETTLE_TOL`], at most [`SETTLE_MAX`] sub-steps), then
    /// takes one more sub-step, as the original's reset does. Refuses a non-finite or absurd state
    /// (any |angle| > 100 rad) without touching the simulator.
    pub fn reset_from(&mut self, qpos: &[f64]) -> Result<[f64; OBS_DIM], EnvError> {
        if qpos.len() != NQ {
            return Err(EnvError::BadState {
                env: ENV_NAME.into(),
                message: format!("initial qpos has {} values, expected {NQ}", qpos.len()),
            });
        }
        if let Some((i, v)) =
            qpos.iter().enumerate().find(|(_, v)| !v.is_finite() || v.abs() > 100.0)
        {
            return Err(EnvError::BadState {
                env: ENV_NAME.into(),
                // `compact`: `{}` would print 1e300 with all its 301 digits.
                message: format!(
                    "initial qpos[{i}] is {} (must be finite, at most 100 rad)",
                    pdt_base::num::compact(*v)
                ),
            });
        }
        let start: [f64; NQ] = std::array::from_fn(|j| qpos[j]);
        Ok(self.start(&start))
    }

    fn start(&mut self, qpos: &[f64; NQ]) -> [f64; OBS_DIM] {
        let init = self.targets.init;
        self.data.reset();
        self.data.qpos_mut().copy_from_slice(qpos);
        self.data.forward();
        let mut pi = PiController::default();
        for _ in 0..SETTLE_MAX {
            self.data.step();
            let q = self.qpos();
            let ctrl = pi.act(&q, &init);
            self.data.ctrl_mut().copy_from_slice(&ctrl);
            let mut err = 0.0;
            for j in 0..NQ {
                err += (q[j] - init[j]).abs();
            }
            if err < SETTLE_TOL {
                break;
            }
        }
        self.data.step();
        self.t = 0;
        self.finished = false;
        self.obs = self.observation();
        self.obs
    }

    /// One environment step at full precision. Errors (leaving the state unchanged) on a wrong
    /// action size, a non-finite value, or a step after the episode ended.
    pub fn step_f64(&mut self, action: &[f32]) -> Result<DialStep, EnvError> {
        if self.finished {
            return Err(EnvError::Finished { env: ENV_NAME.into() });
        }
        if action.len() != ACT_DIM {
            return Err(EnvError::ActionDim {
                env: ENV_NAME.into(),
                got: action.len(),
                expected: ACT_DIM,
            });
        }
        if let Some((index, &value)) = action.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(EnvError::NonFiniteAction { env: ENV_NAME.into(), index, value });
        }
        let ctrl = clip_box(std::array::from_fn(|j| f64::from(action[j])));
        self.data.ctrl_mut().copy_from_slice(&ctrl);
        let mut success = false;
        for _ in 0..ACTION_REPEAT {
            self.data.step();
            if self.distance() < SUCCESS_L1 {
                success = true;
                break;
            }
        }
        self.t += 1;
        let truncated = !success && self.t >= HORIZON;
        self.finished = success || truncated;
        self.obs = self.observation();
        if let Some(i) = self.obs.iter().position(|v| !v.is_finite()) {
            self.finished = true;
            return Err(sim_error(format!(
                "the simulation diverged at step {} (obs[{i}])",
                self.t
            )));
        }
        Ok(DialStep { obs: self.obs, reward: if success { 1.0 } else { 0.0 }, success, truncated })
    }
}

impl Env for Dial {
    fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn act_dim(&self) -> usize {
        ACT_DIM
    }

    fn horizon(&self) -> usize {
        HORIZON
    }

    /// The seed is unused: the reset is deterministic, as the original's.
    fn reset(&mut self, _seed: u64) -> Vec<f32> {
        self.reset_f64().iter().map(|&v| v as f32).collect()
    }

    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError> {
        let s = self.step_f64(action)?;
        Ok(StepResult {
            obs: s.obs.iter().map(|&v| v as f32).collect(),
            reward: s.reward as f32,
            terminated: s.success,
            truncated: s.truncated,
            success: Some(s.success),
        })
    }
    /// A fixed camera on the table: the pin pad in front, the arm beside it.
    fn view(&mut self) -> Result<crate::render::View<'_>, EnvError> {
        let camera = crate::render::Camera::Fixed {
            lookat: [0.4, 0.0, 0.2],
            distance: 1.6,
            azimuth: 200.0,
            elevation: -35.0,
        };
        Ok(crate::render::View::Mujoco { data: &mut self.data, camera })
    }
}

/// A perturbed start pose for data collection: the init pose plus the original collector's noise
/// (see [`START_NOISE`]).
pub fn noisy_start(rng: &mut impl Rng) -> Result<[f64; NQ], EnvError> {
    let init = targets()?.init;
    let mut q: [f64; NQ] =
        std::array::from_fn(|j| init[j] + rng.random_range(-START_NOISE..START_NOISE));
    q[0] += rng.random_range(0.0..0.2);
    q[1] += rng.random_range(-0.2..0.0);
    Ok(q)
}

/// The scripted expert: the original's PI controller toward the digit's hover pose (the Prompt-DT
/// collector's target), once per environment step, reading the joint angles from the observation
/// (f32, widened). Hovering 4 cm above the key already counts as reaching it (the success radius
/// is 10 cm).
#[derive(Debug, Clone)]
pub struct DialExpert {
    target: [f64; NQ],
    pi: PiController,
}

impl DialExpert {
    pub fn new(digit: usize) -> Result<Self, EnvError> {
        let t = targets()?;
        let target = *t.hover.get(digit).ok_or(EnvError::UnknownTask {
            env: ENV_NAME.into(),
            task: digit,
            n: NUM_TASKS,
        })?;
        Ok(Self::with_target(target))
    }

    /// The same controller toward another pose (the medium policy's misremembered target).
    pub fn with_target(target: [f64; NQ]) -> Self {
        Self { target, pi: PiController::default() }
    }

    /// The clean action for observation `obs` (its first 9 values are the joint angles).
    pub fn act(&mut self, obs: &[f32]) -> [f32; ACT_DIM] {
        let q: [f64; NQ] = std::array::from_fn(|j| f64::from(obs[j]));
        self.pi.act(&q, &self.target).map(|v| v as f32)
    }
}

/// Dial: 10 digits, the paper's split.
#[derive(Debug, Clone, Default)]
pub struct DialFamily;

impl DialFamily {
    /// The environment of `task` (a digit), as a concrete type.
    pub fn make_env(&self, task: usize) -> Result<Dial, EnvError> {
        Dial::new(task)
    }
}

impl EnvFamily for DialFamily {
    fn name(&self) -> &str {
        ENV_NAME
    }

    fn num_tasks(&self) -> usize {
        NUM_TASKS
    }

    fn preset(&self) -> EnvPreset {
        EnvPreset {
            obs_dim: OBS_DIM,
            act_dim: ACT_DIM,
            horizon: HORIZON,
            rtg_scale: RTG_SCALE,
            target_return: TARGET_RETURN,
            prompt_length: PROMPT_LENGTH,
        }
    }

    fn split_names(&self) -> Vec<String> {
        vec!["default".into()]
    }

    /// `default`: the paper's train digits [1, 2, 3, 4, 5, 8], test [6, 7, 9, 0].
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        match name {
            "default" => Ok((TRAIN_TASKS.to_vec(), TEST_TASKS.to_vec())),
            other => Err(EnvError::unknown_split(ENV_NAME, other, &["default"])),
        }
    }

    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        EnvError::check_task(ENV_NAME, task, NUM_TASKS)?;
        let t = targets()?;
        Ok(serde_json::json!({ "digit": task, "press_xyz": t.press_xyz[task] }))
    }

    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(self.make_env(task)?))
    }

    /// The controller's box `[C_LOW, C_HIGH]`.
    /// 20 simulator steps of 0.002 s per action.
    fn render_fps(&self) -> u32 {
        25
    }

    fn action_bounds(&self) -> ActionBounds {
        ActionBounds {
            low: C_LOW.iter().map(|&v| v as f32).collect(),
            high: C_HIGH.iter().map(|&v| v as f32).collect(),
        }
    }

    /// [`SUCCESS_REWARD`].
    fn success_reward(&self) -> Option<f32> {
        Some(SUCCESS_REWARD)
    }

    /// Its scripted policies (`collect.rs`).
    fn scripted(&self) -> Option<ScriptedFamily> {
        Some(ScriptedFamily::new(&collect::DialPolicies))
    }

    /// From the digit's deterministic reset, or from `init` = `{"qpos": [9 joint angles]}`
    /// ([`replay_dial`]).
    fn replay(
        &self,
        task: usize,
        init: Option<&str>,
        actions: &[Vec<f32>],
    ) -> Result<ReplayResult, EnvError> {
        replay_dial_init(task, init, actions)
    }
}

/// Replays `actions` on Dial's digit `task` from its deterministic reset, or, with `start_qpos`
/// (9 joint angles), from that pose at rest settled back toward the init pose as a collection
/// episode starts ([`Dial::reset_from`]). The observations are the f32 ones the datasets see.
/// Note: a collected episode with DART noise recorded its clean actions, not the executed ones, so
/// replaying its recorded actions does not reproduce it (`docs/dial.md`).
pub fn replay_dial(
    task: usize,
    start_qpos: Option<&[f64]>,
    actions: &[Vec<f32>],
) -> Result<ReplayResult, EnvError> {
    let mut env = DialFamily.make_env(task)?;
    let first = match start_qpos {
        Some(q) => env.reset_from(q)?,
        None => env.reset_f64(),
    };
    let first = first.iter().map(|&v| v as f32).collect();
    crate::replay::play(
        &mut env,
        ReplayResult::start(ENV_NAME, task, first, actions.len()),
        actions,
    )
}

/// [`crate::EnvFamily::replay`] of Dial: `init` is optional, `{"qpos": [9 joint angles]}`
/// ([`replay_dial`]).
pub fn replay_dial_init(
    task: usize,
    init: Option<&str>,
    actions: &[Vec<f32>],
) -> Result<ReplayResult, EnvError> {
    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Start {
        qpos: Vec<f64>,
    }
    match init {
        None => replay_dial(task, None, actions),
        Some(text) => {
            let s: Start = serde_json::from_str(text).map_err(|e| EnvError::ReplayInit {
                message: format!("expected {{\"qpos\": [9 joint angles]}}: {e}"),
            })?;
            replay_dial(task, Some(&s.qpos), actions)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_compiles_with_the_specified_sizes() {
        let model = load_model().unwrap_or_else(|e| panic!("{e}"));
        let m = model.ffi();
        assert_eq!((m.nq, m.nv, m.nu, m.nbody), (9, 9, 9, 16));
        assert_eq!(model.opt().timestep, 0.002);
    }

    /// The environment with the arm posed at `q` (at rest, kinematics fresh), for geometry checks.
    fn posed(digit: usize, q: &[f64; NQ]) -> Dial {
        let mut env = Dial::new(digit).unwrap_or_else(|e| panic!("{e}"));
        env.data.reset();
        env.data.qpos_mut().copy_from_slice(q);
        env.data.forward();
        env
    }

    #[test]
    fn observation_block_k_is_zero_at_digit_ks_press_pose() {
        let t = targets().unwrap_or_else(|e| panic!("{e}"));
        for k in 0..NUM_TASKS {
            let env = posed(k, &t.press[k]);
            let obs = env.observation();
            let block = &obs[NQ + 3 * k..NQ + 3 * k + 3];
            assert!(block.iter().all(|v| v.abs() < 1e-9), "digit {k}: {block:?}");
            assert!(env.distance() < 1e-9);
            // Every other digit's block is farther than the success radius: the reward of a task
            // cannot fire at another digit's press point.
            for j in (0..NUM_TASKS).filter(|&j| j != k) {
                let b = &obs[NQ + 3 * j..NQ + 3 * j + 3];
                let l1 = b[0].abs() + b[1].abs() + b[2].abs();
                assert!(l1 >= SUCCESS_L1, "digit {k}'s press point is within reach of {j}: {l1}");
            }
        }
    }

    #[test]
    fn poses_hold_the_originals_sign_convention_and_touch_nothing() {
        let t = targets().unwrap_or_else(|e| panic!("{e}"));
        for k in 0..NUM_TASKS {
            for (name, q) in [("press", &t.press[k]), ("hover", &t.hover[k])] {
                let env = posed(k, q);
                // A negative joint-2 torque lifts the arm (the original's action box assumes it).
                let bias = env.data.qfrc_bias()[1];
                assert!(bias < 0.0, "digit {k} {name}: joint-2 gravity bias {bias}");
                assert_eq!(env.data.ffi().ncon, 0, "digit {k} {name}: contacts");
            }
            // The hover point is within the success radius of the press point (as in the
            // original, where reaching the hover pose already counts).
            let hover = posed(k, &t.hover[k]);
            assert!(hover.distance() < SUCCESS_L1, "digit {k}: hover {}", hover.distance());
        }
    }

    #[test]
    fn wrap_is_pythons_floored_modulo() {
        use std::f64::consts::PI;
        assert_eq!(wrap(0.0), 0.0);
        assert!((wrap(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-15);
        assert!((wrap(-3.0 * PI / 2.0) - PI / 2.0).abs() < 1e-15);
        assert_eq!(wrap(PI), -PI);
    }

    #[test]
    fn pi_controller_integrates_a_scalar_sum() {
        let mut pi = PiController::default();
        let q = [0.0; NQ];
        let target = [0.001; NQ];
        let e = wrap(0.001);
        let first = pi.act(&q, &target);
        assert_eq!(first[0], KP[0] * e);
        let second = pi.act(&q, &target);
        // The integral of the first error vector: 9 entries of 0.001, times KI per joint.
        let sum = (0..9).fold(0.0, |s, _| s + e);
        assert_eq!(second[3], KP[3] * e + KI[3] * sum);
        // Clipped to the box.
        let big = PiController::default().act(&q, &[3.0; NQ]);
        assert_eq!(big[1], C_HIGH[1]);
    }
}
