//! The MuJoCo environments of the reference (`promptdt-reference.md` e.1-e.3): one simulator wrapper
//! [`MujocoEnv`] for HalfCheetah-Dir, HalfCheetah-Vel and Ant-Dir, on MuJoCo 3.17.0 through
//! mujoco-rs. The per-family constants, reward functions and task families live in
//! [`crate::cheetah`] and [`crate::ant_dir`], which implement [`MujocoTask`]; this module knows
//! none of them. `docs/mujoco-envs.md` describes them all.
//!
//! What each step does, as gym's `MujocoEnv` did for the reference:
//! 1. `ctrl <- action` (f32 widened to f64; MuJoCo clamps to the ctrlrange [-1, 1] itself),
//! 2. `mj_step` [`FRAME_SKIP`] = 5 times (dt = 5 x 0.01 s),
//! 3. read `qpos`, `qvel` and `xpos(torso)` **as `mj_step` leaves them, without `mj_forward`**.
//!
//! The third point matters (pitfall 22): `mj_step` computes kinematics at the start of its last
//! sub-step, so `xpos` is one 0.01 s sub-step older than `qpos`. The cheetah observation's torso
//! position and Ant-Dir's reward read that stale `xpos`; the reference's recorded data shows it.

use std::sync::{Arc, Once, OnceLock};

use mujoco_rs::prelude::{MjData, MjModel, MjtObjBase};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::{Env, EnvError, StepResult};

/// Simulator steps per environment step (gym's `frame_skip` for both bodies).
pub const FRAME_SKIP: usize = 5;
/// Episode length: `step` reports `truncated` at this step (the reference's `max_ep_len`).
pub const HORIZON: usize = 200;
/// Half-width of the uniform noise added to every `qpos` entry at reset (gym `reset_model`).
pub const RESET_QPOS_NOISE: f64 = 0.1;
/// Standard deviation of the normal noise added to every `qvel` entry at reset.
pub const RESET_QVEL_NOISE: f64 = 0.1;

/// gym's `half_cheetah.xml`, unchanged (md5 6bf6419903e906a511ad88260f424d22).
pub const HALF_CHEETAH_XML: &str = include_str!("../assets/half_cheetah.xml");
/// gym's `ant.xml` with the Ant-Dir sites `goal` and `origin` and without the `track` camera.
pub const ANT_DIR_XML: &str = include_str!("../assets/ant_dir.xml");

/// Which body model a family uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Body {
    HalfCheetah,
    Ant,
}

impl Body {
    fn xml(self) -> &'static str {
        match self {
            Body::HalfCheetah => HALF_CHEETAH_XML,
            Body::Ant => ANT_DIR_XML,
        }
    }

    /// Observation size: cheetah `qpos[1:]` (8) + `qvel` (9) + `xpos(torso)` (3); ant `qpos[2:]`
    /// (13) + `qvel` (14).
    pub fn obs_dim(self) -> usize {
        match self {
            Body::HalfCheetah => 20,
            Body::Ant => 27,
        }
    }

    /// How a frame looks at the body: the cheetah through its model's `track` camera (gym's side
    /// view, following its centre of mass), the ant (whose model has no camera) from a camera
    /// tracking its torso from behind and above.
    pub fn camera(self, model: &MjModel, torso: usize) -> crate::render::Camera {
        let track = model.name_to_id(MjtObjBase::mjOBJ_CAMERA, "track");
        match (self, track) {
            (Body::HalfCheetah, Some(id)) => crate::render::Camera::Model { id },
            (Body::HalfCheetah, None) => crate::render::Camera::Tracking {
                body: torso,
                distance: 3.0,
                azimuth: 90.0,
                elevation: -10.0,
            },
            (Body::Ant, _) => crate::render::Camera::Tracking {
                body: torso,
                distance: 5.0,
                azimuth: 90.0,
                elevation: -35.0,
            },
        }
    }

    /// Number of actuators.
    pub fn act_dim(self) -> usize {
        match self {
            Body::HalfCheetah => 6,
            Body::Ant => 8,
        }
    }
}

/// A family's task: the body it runs on and the reward it pays. The families implement it
/// (`crate::cheetah`, `crate::ant_dir`); this simulator wrapper knows none of them.
pub trait MujocoTask: std::fmt::Debug + Send + Sync {
    fn body(&self) -> Body;
    /// The family name, used in error messages.
    fn env_name(&self) -> &'static str;
    /// The reward of the step just taken and whether it terminated the episode.
    fn reward(&self, step: &mut StepState<'_>, action: &[f32]) -> (f64, bool);
}

/// What a reward may read about the step just taken.
pub struct StepState<'a> {
    /// `qpos[0]` (the root's x) before and after the step.
    pub x_before: f64,
    pub x_after: f64,
    /// The torso's frame position before and after the step, as `mj_step` left it (stale by one
    /// sub-step, see the module docs).
    pub torso_before: [f64; 3],
    pub torso_after: [f64; 3],
    /// Environment time step (0.05 s).
    pub dt: f64,
    data: &'a mut MjData<Arc<MjModel>>,
}

impl StepState<'_> {
    pub fn qpos(&self) -> &[f64] {
        self.data.qpos()
    }

    pub fn qvel(&self) -> &[f64] {
        self.data.qvel()
    }

    /// External contact forces on every body, after `mj_rnePostConstraint` (which fills
    /// `cfrc_ext` and changes no state).
    pub fn contact_forces(&mut self) -> &[[f64; 6]] {
        self.data.rne_post_constraint();
        self.data.cfrc_ext()
    }
}

/// MuJoCo's `mjMAXVAL`: state magnitudes above it count as a diverged simulation.
const MJ_MAXVAL: f64 = 1e10;

/// Routes MuJoCo's log to the `log` crate, once per process, before the first model is loaded.
///
/// Without this MuJoCo prints warnings to stdout and appends them to `MUJOCO_LOG.TXT` in the
/// working directory (gym's `half_cheetah.xml` triggers one at every load: `settotalmass` is
/// deprecated). The `log` crate lets the program decide where they go.
pub(crate) fn init_logging() {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        // SAFETY: mujoco-rs requires that no other thread uses MuJoCo during the call. Every MuJoCo
        // use in this crate goes through `load_model`, which runs this `Once` first; `call_once`
        // blocks every other caller until it has returned. So no thread of this crate can be
        // using MuJoCo while the hook is installed.
        #[allow(unsafe_code)]
        unsafe {
            mujoco_rs::prelude::install_logging_hook()
        };
    });
}

/// The compiled model of `body`, loaded once per process and shared (read-only) by every
/// environment.
fn load_model(body: Body) -> Result<Arc<MjModel>, EnvError> {
    static CHEETAH: OnceLock<Result<Arc<MjModel>, String>> = OnceLock::new();
    static ANT: OnceLock<Result<Arc<MjModel>, String>> = OnceLock::new();
    init_logging();
    let cell = match body {
        Body::HalfCheetah => &CHEETAH,
        Body::Ant => &ANT,
    };
    let loaded = cell.get_or_init(|| {
        MjModel::from_xml_string(body.xml()).map(Arc::new).map_err(|e| format!("{e:?}"))
    });
    loaded.clone().map_err(|message| EnvError::Simulation {
        env: format!("{body:?}"),
        message: format!("cannot load the MuJoCo model: {message}"),
    })
}

/// One MuJoCo environment instance (see the module docs).
#[derive(Debug)]
pub struct MujocoEnv {
    task: Box<dyn MujocoTask>,
    data: MjData<Arc<MjModel>>,
    /// Body id of `torso` (1 in both models).
    torso: usize,
    /// The model's default pose `qpos0` and zero velocity: gym's `init_qpos`/`init_qvel`.
    init_qpos: Vec<f64>,
    init_qvel: Vec<f64>,
    /// Environment time step: `timestep * FRAME_SKIP` (0.05 s), computed like gym's `dt`.
    dt: f64,
    /// Steps taken in the current episode.
    t: usize,
    /// The episode has ended (terminated or truncated); `step` refuses until the next reset.
    finished: bool,
}

impl MujocoEnv {
    /// An environment for `task`, already reset with seed 0 (so `step` may be called at once).
    pub fn new(task: Box<dyn MujocoTask>) -> Result<Self, EnvError> {
        let model = load_model(task.body())?;
        let torso = model.name_to_id(MjtObjBase::mjOBJ_BODY, "torso").ok_or_else(|| {
            EnvError::Simulation {
                env: task.env_name().into(),
                message: "model has no body `torso`".into(),
            }
        })?;
        let init_qpos = model.qpos0().to_vec();
        let dt = model.opt().timestep * FRAME_SKIP as f64;
        let data = MjData::try_new(model).map_err(|e| EnvError::Simulation {
            env: task.env_name().into(),
            message: format!("cannot allocate mjData: {e:?}"),
        })?;
        let init_qvel = vec![0.0; data.qvel().len()];
        let mut env = Self { task, data, torso, init_qpos, init_qvel, dt, t: 0, finished: false };
        env.reset(0);
        Ok(env)
    }

    pub fn task(&self) -> &dyn MujocoTask {
        self.task.as_ref()
    }

    /// Environment time step in seconds (0.05).
    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// Number of position coordinates (cheetah 9, ant 15).
    pub fn nq(&self) -> usize {
        self.init_qpos.len()
    }

    /// Number of velocity coordinates (cheetah 9, ant 14).
    pub fn nv(&self) -> usize {
        self.init_qvel.len()
    }

    /// The current generalised positions.
    pub fn qpos(&self) -> &[f64] {
        self.data.qpos()
    }

    /// The current generalised velocities.
    pub fn qvel(&self) -> &[f64] {
        self.data.qvel()
    }

    /// The torso's frame position as the last `mj_step` (or the reset's `mj_forward`) left it:
    /// after a step it is one sub-step older than [`qpos`](Self::qpos) (see the module docs).
    pub fn torso_xpos(&self) -> [f64; 3] {
        self.data.xpos().get(self.torso).copied().unwrap_or([f64::NAN; 3])
    }

    /// The default pose `qpos0` that reset noise is added to.
    pub fn init_qpos(&self) -> &[f64] {
        &self.init_qpos
    }

    /// Steps taken in the current episode.
    pub fn steps(&self) -> usize {
        self.t
    }

    /// Starts an episode from exactly `qpos`, `qvel` (no noise): what `reset` does after drawing
    /// its noise, as gym's `set_state`: `mj_resetData`, set the state, `mj_forward`.
    pub fn reset_to(&mut self, qpos: &[f64], qvel: &[f64]) -> Result<Vec<f32>, EnvError> {
        let env = self.task.env_name();
        for (what, values, expected) in [("qpos", qpos, self.nq()), ("qvel", qvel, self.nv())] {
            if values.len() != expected {
                return Err(EnvError::BadState {
                    env: env.into(),
                    message: format!("{what} has {} values, expected {expected}", values.len()),
                });
            }
            if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(EnvError::BadState {
                    env: env.into(),
                    message: format!("{what}[{i}] is {v}, not a finite number"),
                });
            }
            // MuJoCo treats a magnitude above mjMAXVAL as a diverged simulation and silently
            // resets it at the next step (mjWARN_BADQPOS / BADQVEL): refuse it here instead.
            if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| v.abs() > MJ_MAXVAL) {
                return Err(EnvError::BadState {
                    env: env.into(),
                    message: format!(
                        "{what}[{i}] is {v:e}, beyond MuJoCo's limit of {MJ_MAXVAL:e} (it would \
                         reset the simulation)"
                    ),
                });
            }
        }
        self.set_state(qpos, qvel);
        Ok(self.observation())
    }

    /// How many times MuJoCo has found this simulation diverged (bad qpos, qvel or qacc) and
    /// reset it since the last reset; a replay reports the step where this happens.
    pub fn instability_resets(&self) -> i64 {
        // mjtWarning: mjWARN_BADQPOS = 3, mjWARN_BADQVEL = 4, mjWARN_BADQACC = 5.
        let w = self.data.warning();
        [3usize, 4, 5].iter().map(|&i| i64::from(w[i].number)).sum()
    }

    fn set_state(&mut self, qpos: &[f64], qvel: &[f64]) {
        // mj_resetData also zeroes time, controls, warm-start accelerations and contacts, so an
        // episode does not depend on the previous one.
        self.data.reset();
        self.data.qpos_mut().copy_from_slice(qpos);
        self.data.qvel_mut().copy_from_slice(qvel);
        // Fresh kinematics at reset (here xpos matches qpos exactly, unlike after a step).
        self.data.forward();
        self.t = 0;
        self.finished = false;
    }

    /// The observation of the current state, in f32 (see [`Body::obs_dim`]).
    fn observation(&self) -> Vec<f32> {
        let qpos = self.data.qpos();
        let qvel = self.data.qvel();
        let mut obs = Vec::with_capacity(self.task.body().obs_dim());
        match self.task.body() {
            Body::HalfCheetah => {
                obs.extend(qpos[1..].iter().map(|&v| v as f32));
                obs.extend(qvel.iter().map(|&v| v as f32));
                obs.extend(self.torso_xpos().iter().map(|&v| v as f32));
            }
            Body::Ant => {
                obs.extend(qpos[2..].iter().map(|&v| v as f32));
                obs.extend(qvel.iter().map(|&v| v as f32));
            }
        }
        obs
    }

    fn check_action(&self, action: &[f32]) -> Result<(), EnvError> {
        let env = self.task.env_name();
        if self.finished {
            return Err(EnvError::Finished { env: env.into() });
        }
        let expected = self.task.body().act_dim();
        if action.len() != expected {
            return Err(EnvError::ActionDim { env: env.into(), got: action.len(), expected });
        }
        if let Some((index, &value)) = action.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            // MuJoCo would only warn and reset the simulation: a non-finite action is a policy
            // bug, so refuse it before it reaches the simulator.
            return Err(EnvError::NonFiniteAction { env: env.into(), index, value });
        }
        // The control cost sums the squares in f64 and the reward is stored in f32: beyond this
        // bound a finite action could give an infinite reward (found by tests/it/replay_fuzz.rs).
        if let Some((index, &value)) =
            action.iter().enumerate().find(|(_, v)| v.abs() > MAX_ACTION_MAGNITUDE)
        {
            return Err(EnvError::ActionTooLarge {
                env: env.into(),
                index,
                value,
                limit: MAX_ACTION_MAGNITUDE,
            });
        }
        Ok(())
    }
}

/// The largest action magnitude a MuJoCo family accepts: squares up to 1e30, so a control cost of
/// any weight up to 1 over 8 actuators stays far below f32's limit (3.4e38). MuJoCo clamps the
/// controls to [-1, 1], so no meaningful action comes near it.
pub const MAX_ACTION_MAGNITUDE: f32 = 1e15;

impl Env for MujocoEnv {
    fn obs_dim(&self) -> usize {
        self.task.body().obs_dim()
    }

    fn act_dim(&self) -> usize {
        self.task.body().act_dim()
    }

    fn horizon(&self) -> usize {
        HORIZON
    }

    /// gym's `reset_model`: `qpos = qpos0 + U(-0.1, 0.1)`, then `qvel = 0 + 0.1 N(0, 1)`, all drawn
    /// from `ChaCha8Rng::seed_from_u64(seed)` (positions first, in coordinate order).
    fn reset(&mut self, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let qpos: Vec<f64> = self
            .init_qpos
            .iter()
            .map(|&q| q + rng.random_range(-RESET_QPOS_NOISE..RESET_QPOS_NOISE))
            .collect();
        let qvel: Vec<f64> = self
            .init_qvel
            .iter()
            .map(|&v| v + RESET_QVEL_NOISE * standard_normal(&mut rng))
            .collect();
        self.set_state(&qpos, &qvel);
        self.observation()
    }

    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError> {
        // Everything is checked before the simulator changes, so a refused step leaves the episode
        // as it was.
        self.check_action(action)?;
        let x_before = self.data.qpos()[0];
        let p_before = self.torso_xpos();
        for (c, &a) in self.data.ctrl_mut().iter_mut().zip(action) {
            *c = f64::from(a);
        }
        for _ in 0..FRAME_SKIP {
            self.data.step();
        }
        // No mj_forward here: the observation and Ant-Dir's reward read xpos as mj_step left it.
        let x_after = self.data.qpos()[0];
        let p_after = self.torso_xpos();
        let mut state = StepState {
            x_before,
            x_after,
            torso_before: p_before,
            torso_after: p_after,
            dt: self.dt,
            data: &mut self.data,
        };
        let (reward, terminated) = self.task.reward(&mut state, action);
        self.t += 1;
        let truncated = !terminated && self.t >= HORIZON;
        self.finished = terminated || truncated;
        Ok(StepResult {
            obs: self.observation(),
            reward: reward as f32,
            terminated,
            truncated,
            success: None,
        })
    }
    /// The body's camera (see [`Body::camera`]).
    fn view(&mut self) -> Result<crate::render::View<'_>, EnvError> {
        let camera = self.task.body().camera(self.data.model(), self.torso);
        Ok(crate::render::View::Mujoco { data: &mut self.data, camera })
    }
}

/// A standard normal sample (Box-Muller, [`pdt_base::standard_normal`]) from two uniforms of
/// `rng`; the crate's environments and scripted collectors all draw their noise through it.
pub(crate) fn standard_normal(rng: &mut ChaCha8Rng) -> f64 {
    pdt_base::standard_normal(|| rng.random::<f64>())
}

/// Sum of squares of the action, accumulated in f64 in coordinate order (the control cost's
/// `||a||^2`; the Python replay script sums the same way, so rewards agree bit for bit).
pub fn action_sq_norm(action: &[f32]) -> f64 {
    action.iter().fold(0.0, |acc, &a| acc + f64::from(a) * f64::from(a))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cheetah() -> MujocoEnv {
        match MujocoEnv::new(Box::new(crate::cheetah::CheetahDirTask { direction: 1.0 })) {
            Ok(env) => env,
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn an_action_whose_cost_would_overflow_the_reward_is_refused_and_changes_nothing() {
        // tests/it/replay_fuzz.rs found it: ctrl 1.34e33 gave a reward of -inf in f32.
        let mut env = cheetah();
        let obs = env.reset(0);
        let err = env.step(&[0.0, 0.0, 1.342_946_4e33, -1e10, 0.0, 0.0]).expect_err("refused");
        assert!(matches!(err, EnvError::ActionTooLarge { index: 2, .. }), "{err}");
        assert!(err.to_string().contains("action[2]"), "{err}");
        assert_eq!(env.steps(), 0);
        assert_eq!(env.observation(), obs);
        let ok = env.step(&[0.0, 0.0, 1e15, -1e15, 0.0, 0.0]).expect("at the bound");
        assert!(ok.reward.is_finite(), "{}", ok.reward);
    }

    #[test]
    fn cheetah_torso_xpos_is_one_substep_stale_after_a_step() {
        let mut env = cheetah();
        env.reset(3);
        let r = env.step(&[0.5, -0.3, 0.9, -1.0, 0.2, 0.7]).map_err(|e| e.to_string());
        let r = r.unwrap_or_else(|e| panic!("{e}"));
        let (x, vx) = (env.qpos()[0], env.qvel()[0]);
        let stale = env.torso_xpos()[0];
        // Semi-implicit Euler: x_new = x_old + h v_new, and xpos was computed at x_old.
        assert!((stale - (x - 0.01 * vx)).abs() < 1e-9, "stale {stale} vs {}", x - 0.01 * vx);
        assert!((stale - x).abs() > 1e-4, "the step should have moved the torso");
        assert_eq!(r.obs[17], stale as f32);
        // mj_forward would make it fresh: the environment must not call it.
        env.data.forward();
        assert!((env.torso_xpos()[0] - x).abs() < 1e-12);
    }

    #[test]
    fn reset_xpos_is_fresh() {
        let mut env = cheetah();
        let obs = env.reset(11);
        assert_eq!(obs[17], env.qpos()[0] as f32);
        assert_eq!(obs[19], (0.7 + env.qpos()[1]) as f32);
    }

    #[test]
    fn dt_is_five_substeps() {
        assert_eq!(cheetah().dt(), 0.05);
    }
}
