//! Meta-World reach (`metaworld_reach`): the paper's "Meta-World reach-v2" family (sec. 5.1), on
//! MuJoCo 3.17 with Meta-World's own Sawyer scene. `docs/metaworld-reach.md` describes it; the
//! numbers come from `shared/reference/metaworld-reach.md` (cited below as "spec §n").
//!
//! The executable reference is `metaworld==3.1.1` `reach-v3` with `reward_function_version="v2"`
//! (the 2021 reach-v2 reward), patched for MuJoCo 3.17 as the spec §2.4 says. This module follows
//! its code paths (spec §2), not those of the 2021 mujoco-py code that Prompt-DT ran; the
//! deliberate differences from that legacy code are marked `LEGACY DIFFERENCE` where they live.
//! `scripts/metaworld/replay.py` is a Python twin; `tests/it/metaworld_parity.rs` replays its
//! fixtures and requires bit-equal observations and rewards, and the twin was checked bit for bit
//! against metaworld 3.1.1 itself (`replay.py check`).
//!
//! - Scene: `sawyer_xyz/sawyer_reach_v3.xml` and the 22 files it includes, from the metaworld 3.1.1
//!   wheel (`scripts/fetch_metaworld.py`, run by `build.rs`), embedded in the library and loaded
//!   through a MuJoCo virtual file system.
//! - Action (4, f32): hand displacement `clip(a[0..3], -1, 1) * 0.01` (an f32 product) added to the
//!   mocap position, which is clipped to the hand box; gripper ctrl `(a3, -a3)` (MuJoCo clamps).
//! - Step: 5 x `mj_step` (dt 0.0125 s), then `mj_forward` (fresh kinematics for obs and reward).
//! - Observation (39): hand xyz, gripper opening, object xyz, object quaternion (x, y, z, w),
//!   7 zeros; the previous step's 18 values (at reset: the current ones); the goal, or zeros when
//!   the goal is hidden (ML1 tasks, the family default).
//! - Reward: `10 * tolerance(‖tcp − goal‖)` (long tail, bounds [0, 0.05], margin
//!   ‖hand_init − goal‖); success when ‖tcp − goal‖ <= 0.05. Episodes never terminate; they are
//!   truncated at 500 steps.
//!
//! Its datasets are collected by the scripted policies of `collect.rs` (`ReachPolicies`:
//! Meta-World's `SawyerReachV3Policy` with noise), on the machinery every scripted family shares
//! (`collect_scripted`).

use std::sync::{Arc, OnceLock};

use mujoco_rs::prelude::{MjData, MjModel, MjtObjBase};
use mujoco_rs::wrappers::MjVfs;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::collect_scripted::ScriptedFamily;
use crate::replay::{replay_from_reset, ReplayResult};
use crate::{ActionBounds, Env, EnvError, EnvFamily, EnvPreset, StepResult};

/// Family name, as used in file names.
pub const ENV_NAME: &str = "metaworld_reach";
pub const OBS_DIM: usize = 39;
pub const ACT_DIM: usize = 4;
/// Meta-World's `max_path_length` for every v2/v3 environment (spec §2.3).
pub const HORIZON: usize = 500;
/// Simulator steps per environment step (timestep 0.0025 s, from the scene).
pub const FRAME_SKIP: usize = 5;
/// Tasks of an ML1 task list.
pub const NUM_TASKS: usize = 50;
/// The paper's split (Prompt-DT Table 5), as indices into the ML1 train-task list (see
/// [`MetaWorldReachFamily`] for the mapping).
pub const TRAIN_TASKS: [usize; 15] = [1, 2, 3, 4, 5, 7, 8, 10, 11, 12, 13, 14, 17, 18, 19];
pub const TEST_TASKS: [usize; 5] = [6, 9, 15, 16, 20];

/// Where the hand is held at reset, and the reference point of the reward's margin.
pub const HAND_INIT_POS: [f64; 3] = [0.0, 0.6, 0.2];
/// The box the mocap (hand target) is clipped to: reach's `hand_low` / `hand_high`.
pub const HAND_LOW: [f64; 3] = [-0.5, 0.40, 0.05];
pub const HAND_HIGH: [f64; 3] = [0.5, 1.0, 0.5];
/// Meta-World's `_HAND_SPACE`: observation clip bounds of the hand (never binding for reach).
const HAND_SPACE_LOW: [f64; 3] = [-0.525, 0.348, -0.0525];
const HAND_SPACE_HIGH: [f64; 3] = [0.525, 1.025, 0.7];
/// Task vectors are drawn uniformly from this box: object xyz, then goal xyz (spec §2.3).
pub const RESET_LOW: [f64; 6] = [-0.1, 0.6, 0.02, -0.1, 0.8, 0.05];
pub const RESET_HIGH: [f64; 6] = [0.1, 0.7, 0.02, 0.1, 0.9, 0.3];
/// Success radius and the tolerance's flat region.
pub const TARGET_RADIUS: f64 = 0.05;
/// The reward of a step that succeeded: `10 * tolerance` is exactly 10 where the distance is within
/// [`TARGET_RADIUS`] and below 10 elsewhere, so a recorded (f32) reward of 10 marks success. After
/// the rounding to f32 this also counts distances up to about 2e-5 m beyond the radius (tolerance
/// above 1 - 5e-8); the environment's own `success` flag is exact.
pub const SUCCESS_REWARD: f32 = 10.0;
/// Mocap orientation Meta-World writes before every step (unnormalised; MuJoCo normalises it).
const MOCAP_QUAT: [f64; 4] = [1.0, 0.0, 1.0, 0.0];
/// Hand displacement per unit action, applied as an f32 product (spec §2.7).
const ACTION_SCALE: f32 = 0.01;
/// metaworld 3.x weld parameters: anchor 0, relpos 0, relquat (-1, 0, 0, 0), torquescale 5 (tuned
/// by Farama for MuJoCo 3's mocap weld, PR #493). MuJoCo 3.17 has a 12th `eq_data` number
/// (mjNEQDATA = 12) that metaworld does not know; like the patched metaworld, it is left as
/// compiled.
/// LEGACY DIFFERENCE: the 2021 code (MuJoCo 2.0) wrote relquat (+1, 0, 0, 0) and torquescale 1.
const WELD_EQ_DATA: [f64; 11] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0];
/// Hand-reset loop at every reset: 50 x (hold the mocap at `HAND_INIT_POS`, 5 sub-steps).
const RESET_HAND_STEPS: usize = 50;

/// Prompt-DT's return-to-go divisor for Meta-World: `gen_env`'s ML1 branch (`scale = 650`), the
/// only Meta-World setting in its code. The paper gives none for reach (spec §4.2 d).
pub const RTG_SCALE: f32 = 650.0;
/// G* of the paper's Table 3 (1500; expert returns are about 4840: spec §4.2 d).
pub const TARGET_RETURN: f32 = 1500.0;
/// Prompt length K* of the paper's Table 3.
pub const PROMPT_LENGTH: usize = 2;

/// The scene files, paths relative to Meta-World's `assets/` (the includes are relative, so the
/// tree is kept), embedded at compile time from `third_party/metaworld/` (fetched by `build.rs`).
macro_rules! asset {
    ($path:literal) => {
        (
            $path,
            include_bytes!(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/../../third_party/metaworld/assets/",
                $path
            )) as &[u8],
        )
    };
}
const SCENE: &str = "sawyer_xyz/sawyer_reach_v3.xml";
const ASSETS: [(&str, &[u8]); 23] = [
    asset!("sawyer_xyz/sawyer_reach_v3.xml"),
    asset!("scene/basic_scene.xml"),
    asset!("objects/assets/block_dependencies.xml"),
    asset!("objects/assets/xyz_base_dependencies.xml"),
    asset!("objects/assets/xyz_base.xml"),
    asset!("objects/meshes/table/tablebody.stl"),
    asset!("objects/meshes/table/tabletop.stl"),
    asset!("objects/meshes/block/block.stl"),
    asset!("objects/meshes/xyz_base/base.stl"),
    asset!("objects/meshes/xyz_base/eGripperBase.stl"),
    asset!("objects/meshes/xyz_base/head.stl"),
    asset!("objects/meshes/xyz_base/l0.stl"),
    asset!("objects/meshes/xyz_base/l1.stl"),
    asset!("objects/meshes/xyz_base/l2.stl"),
    asset!("objects/meshes/xyz_base/l3.stl"),
    asset!("objects/meshes/xyz_base/l4.stl"),
    asset!("objects/meshes/xyz_base/l5.stl"),
    asset!("objects/meshes/xyz_base/l6.stl"),
    asset!("objects/meshes/xyz_base/pedestal.stl"),
    asset!("textures/wood2.png"),
    asset!("textures/floor2.png"),
    asset!("textures/metal.png"),
    asset!("textures/wood4.png"),
];

fn sim_error(message: String) -> EnvError {
    EnvError::Simulation { env: ENV_NAME.into(), message }
}

/// The compiled scene with metaworld's weld parameters, loaded once per process and shared
/// (read-only) by every environment.
fn load_model() -> Result<Arc<MjModel>, EnvError> {
    static MODEL: OnceLock<Result<Arc<MjModel>, String>> = OnceLock::new();
    crate::mujoco_env::init_logging();
    let loaded = MODEL.get_or_init(|| {
        let mut vfs = MjVfs::new();
        for (path, bytes) in ASSETS {
            vfs.add_from_buffer(path, bytes).map_err(|e| format!("{path}: {e:?}"))?;
        }
        let mut model = MjModel::from_xml_vfs(SCENE, &vfs).map_err(|e| format!("{e:?}"))?;
        // metaworld's `reset_mocap_welds`: every weld gets the 3.x parameters. The scene has one
        // equality constraint, the mocap-hand weld.
        if model.ffi().neq != 1 || model.ffi().nmocap != 1 {
            return Err(format!(
                "expected one weld and one mocap body, found neq {} nmocap {}",
                model.ffi().neq,
                model.ffi().nmocap
            ));
        }
        // SAFETY: eq_data holds plain numbers with no invariant MuJoCo relies on beyond being
        // finite; this writes the 11 finite values metaworld writes, into the weld's row (the
        // only row: checked above), before any mjData exists.
        #[allow(unsafe_code)]
        let eq_data = unsafe { model.eq_data_mut() };
        eq_data[0][..WELD_EQ_DATA.len()].copy_from_slice(&WELD_EQ_DATA);
        Ok(Arc::new(model))
    });
    loaded.clone().map_err(|m| sim_error(format!("cannot load the Meta-World reach scene: {m}")))
}

mod tasks;
pub use tasks::{ml1_tasks, NumpyRandomState, TaskList};

// The scripted policies that collect the datasets (the machinery: `collect_scripted`).
mod collect;
pub use collect::{run_reach_episode, REACH_ACTION_NOISE, REACH_MEDIUM_GOAL_NOISE};

// ------------------------------------------------------------------------------------------------
// The environment
// ------------------------------------------------------------------------------------------------

/// One step at full precision: what Meta-World returns (observation and reward in f64).
#[derive(Debug, Clone, PartialEq)]
pub struct ReachStep {
    pub obs: [f64; OBS_DIM],
    pub reward: f64,
    /// ‖tcp − goal‖ <= 0.05 after the step (Meta-World's `info["success"]`).
    pub success: bool,
    /// Distance of the gripper's centre point to the goal (`info["obj_to_target"]`).
    pub distance: f64,
    /// The 500th step of the episode.
    pub truncated: bool,
}

/// Ids of what the environment reads from the simulation.
#[derive(Debug, Clone, Copy)]
struct Ids {
    hand: usize,
    right_claw: usize,
    left_claw: usize,
    obj: usize,
    obj_geom: usize,
    right_site: usize,
    left_site: usize,
}

/// One reach task (see the module docs).
#[derive(Debug)]
pub struct MetaWorldReach {
    data: MjData<Arc<MjModel>>,
    ids: Ids,
    obj_init: [f64; 3],
    goal: [f64; 3],
    goal_visible: bool,
    /// ‖HAND_INIT_POS − goal‖: the reward's tolerance margin.
    margin: f64,
    /// The previous step's 18 frame values, unclipped (Meta-World's `_prev_obs`).
    prev: [f64; 18],
    /// The latest observation (the reset's or a step's).
    obs: [f64; OBS_DIM],
    t: usize,
    finished: bool,
}

impl MetaWorldReach {
    /// The task with vector `rand_vec` (object xyz, then goal xyz), already reset. With
    /// `goal_visible = false` the observation's goal slot is zero, as in ML1 tasks; the true goal
    /// stays available through [`goal`](Self::goal) (for the scripted expert).
    pub fn new(rand_vec: [f64; 6], goal_visible: bool) -> Result<Self, EnvError> {
        if let Some((i, v)) = rand_vec.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(EnvError::BadState {
                env: ENV_NAME.into(),
                message: format!("task vector[{i}] is {v}, not a finite number"),
            });
        }
        let model = load_model()?;
        let id = |kind: MjtObjBase, name: &str| {
            model
                .name_to_id(kind, name)
                .ok_or_else(|| sim_error(format!("the scene has no {name}")))
        };
        let ids = Ids {
            hand: id(MjtObjBase::mjOBJ_BODY, "hand")?,
            right_claw: id(MjtObjBase::mjOBJ_BODY, "rightclaw")?,
            left_claw: id(MjtObjBase::mjOBJ_BODY, "leftclaw")?,
            obj: id(MjtObjBase::mjOBJ_BODY, "obj")?,
            obj_geom: id(MjtObjBase::mjOBJ_GEOM, "objGeom")?,
            right_site: id(MjtObjBase::mjOBJ_SITE, "rightEndEffector")?,
            left_site: id(MjtObjBase::mjOBJ_SITE, "leftEndEffector")?,
        };
        let data = MjData::try_new(model)
            .map_err(|e| sim_error(format!("cannot allocate mjData: {e:?}")))?;
        let goal = [rand_vec[3], rand_vec[4], rand_vec[5]];
        let margin = norm3(sub3(HAND_INIT_POS, goal));
        let mut env = Self {
            data,
            ids,
            obj_init: [rand_vec[0], rand_vec[1], rand_vec[2]],
            goal,
            goal_visible,
            margin,
            prev: [0.0; 18],
            obs: [0.0; OBS_DIM],
            t: 0,
            finished: false,
        };
        env.reset_f64();
        Ok(env)
    }

    /// The goal position (also when the observation hides it).
    pub fn goal(&self) -> [f64; 3] {
        self.goal
    }

    /// The object's initial position.
    pub fn obj_init(&self) -> [f64; 3] {
        self.obj_init
    }

    pub fn goal_visible(&self) -> bool {
        self.goal_visible
    }

    /// The latest observation at full precision.
    pub fn obs_f64(&self) -> &[f64; OBS_DIM] {
        &self.obs
    }

    /// Steps taken in the current episode.
    pub fn steps(&self) -> usize {
        self.t
    }

    /// The noiseless scripted expert's action for the current state (see [`expert_action`]).
    pub fn expert_action(&self) -> [f32; ACT_DIM] {
        expert_action([self.obs[0], self.obs[1], self.obs[2]], self.goal)
    }

    /// Meta-World's `reset` (3.x, spec §2.6): `mj_resetData`; 50 times hold the mocap at the hand's
    /// initial position with the gripper driven open-ish (ctrl (-1, 1)) and take 5 sub-steps; place
    /// the object (its settled orientation is kept, its velocity zeroed); `mj_forward`.
    /// Returns the first observation, whose previous-frame half is a copy of the current frame.
    ///
    /// LEGACY DIFFERENCE: the 2021 code kept the previous episode's last frame in obs[18..36].
    pub fn reset_f64(&mut self) -> [f64; OBS_DIM] {
        self.data.reset();
        for _ in 0..RESET_HAND_STEPS {
            self.data.mocap_pos_mut()[0] = HAND_INIT_POS;
            self.data.mocap_quat_mut()[0] = MOCAP_QUAT;
            self.data.ctrl_mut().copy_from_slice(&[-1.0, 1.0]);
            for _ in 0..FRAME_SKIP {
                self.data.step();
            }
        }
        let qpos = self.data.qpos_mut();
        qpos[9..12].copy_from_slice(&self.obj_init);
        self.data.qvel_mut()[9..15].fill(0.0);
        self.data.forward();
        let frame = self.frame();
        self.prev = frame;
        // Meta-World does not clip the reset observation (only step's).
        self.obs = self.observation(&frame);
        self.t = 0;
        self.finished = false;
        self.obs
    }

    /// Meta-World's `step` (3.x order, spec §2.7), at full precision. Errors (leaving the state
    /// unchanged) on a wrong action size, a non-finite value, or a step after the 500th.
    pub fn step_f64(&mut self, action: &[f32]) -> Result<ReachStep, EnvError> {
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
            // Meta-World would clip NaN to NaN and hand it to MuJoCo: a policy bug, refused here.
            return Err(EnvError::NonFiniteAction { env: ENV_NAME.into(), index, value });
        }
        let mocap = &mut self.data.mocap_pos_mut()[0];
        for i in 0..3 {
            // f32 clip and f32 product, widened and added to the f64 mocap position.
            let delta = action[i].clamp(-1.0, 1.0) * ACTION_SCALE;
            mocap[i] = (mocap[i] + f64::from(delta)).clamp(HAND_LOW[i], HAND_HIGH[i]);
        }
        self.data.mocap_quat_mut()[0] = MOCAP_QUAT;
        let grip = f64::from(action[3]);
        self.data.ctrl_mut().copy_from_slice(&[grip, -grip]);
        for _ in 0..FRAME_SKIP {
            self.data.step();
        }
        // LEGACY DIFFERENCE: metaworld 3.x refreshes the kinematics here; the 2021 code read them
        // as mj_step left them, one sub-step stale (spec §5.3).
        self.data.forward();
        self.t += 1;
        let frame = self.frame();
        let mut obs = self.observation(&frame);
        self.prev = frame;
        // Meta-World clips the step observation to its observation space: hand and gripper bounds
        // of both frames (objects are unbounded, the goal slot holds its own bounds' values).
        for base in [0, 18] {
            for i in 0..3 {
                obs[base + i] = obs[base + i].clamp(HAND_SPACE_LOW[i], HAND_SPACE_HIGH[i]);
            }
            obs[base + 3] = obs[base + 3].clamp(-1.0, 1.0);
        }
        self.obs = obs;
        let xpos = self.data.site_xpos();
        let (r, l) = (xpos[self.ids.right_site], xpos[self.ids.left_site]);
        let tcp = [(r[0] + l[0]) / 2.0, (r[1] + l[1]) / 2.0, (r[2] + l[2]) / 2.0];
        let distance = norm3(sub3(tcp, self.goal));
        let reward = 10.0 * tolerance_long_tail(distance, self.margin);
        let truncated = self.t >= HORIZON;
        self.finished = truncated;
        Ok(ReachStep { obs, reward, success: distance <= TARGET_RADIUS, distance, truncated })
    }

    /// The current frame's 18 values: hand, gripper opening, object position and quaternion,
    /// zero padding.
    fn frame(&self) -> [f64; 18] {
        let xpos = self.data.xpos();
        let mut f = [0.0; 18];
        f[0..3].copy_from_slice(&xpos[self.ids.hand]);
        let apart = norm3(sub3(xpos[self.ids.right_claw], xpos[self.ids.left_claw]));
        f[3] = (apart / 0.1).clamp(0.0, 1.0);
        f[4..7].copy_from_slice(&xpos[self.ids.obj]);
        f[7..11].copy_from_slice(&quat_from_matrix(&self.data.geom_xmat()[self.ids.obj_geom]));
        f
    }

    fn observation(&self, frame: &[f64; 18]) -> [f64; OBS_DIM] {
        let mut obs = [0.0; OBS_DIM];
        obs[0..18].copy_from_slice(frame);
        obs[18..36].copy_from_slice(&self.prev);
        if self.goal_visible {
            obs[36..39].copy_from_slice(&self.goal);
        }
        obs
    }
}

impl Env for MetaWorldReach {
    fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn act_dim(&self) -> usize {
        ACT_DIM
    }

    fn horizon(&self) -> usize {
        HORIZON
    }

    /// The seed is unused: a Meta-World task has no start-state noise (its task vector is frozen),
    /// so every reset gives the same state.
    fn reset(&mut self, _seed: u64) -> Vec<f32> {
        self.reset_f64().iter().map(|&v| v as f32).collect()
    }

    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError> {
        let s = self.step_f64(action)?;
        Ok(StepResult {
            obs: s.obs.iter().map(|&v| v as f32).collect(),
            reward: s.reward as f32,
            terminated: false,
            truncated: s.truncated,
            success: Some(s.success),
        })
    }
    /// A fixed camera in front of the table, looking at the arm and the reach area.
    fn view(&mut self) -> Result<crate::render::View<'_>, EnvError> {
        let camera = crate::render::Camera::Fixed {
            lookat: [0.0, 0.65, 0.15],
            distance: 1.7,
            azimuth: 135.0,
            elevation: -25.0,
        };
        Ok(crate::render::View::Mujoco { data: &mut self.data, camera })
    }
}

fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `np.linalg.norm` of a 3-vector as OpenBLAS's Haswell/Zen kernels compute it: the squares summed
/// left to right, no fused multiply-add. (Its AVX-512 kernel fuses them and so differs in the last
/// bit now and then; `docs/metaworld-reach.md`, "Parity".)
fn norm3(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// Meta-World's `reward_utils.tolerance(d, bounds=(0, 0.05), margin, sigmoid="long_tail",
/// value_at_margin=0.1)`, in its order of operations.
pub fn tolerance_long_tail(d: f64, margin: f64) -> f64 {
    if (0.0..=TARGET_RADIUS).contains(&d) {
        return 1.0;
    }
    let x = (d - TARGET_RADIUS) / margin;
    // sqrt(1 / 0.1 - 1) is exactly 3.0 in f64.
    let z = x * 3.0;
    1.0 / (z * z + 1.0)
}

/// scipy's `Rotation.from_matrix(m).as_quat()` (x, y, z, w, not canonicalised) for a proper
/// rotation matrix, row-major: the branch on the largest of the diagonal and the trace, then a
/// division by the norm (spec §2.8; bitwise equal to scipy 1.17 on MuJoCo's matrices).
pub fn quat_from_matrix(m: &[f64; 9]) -> [f64; 4] {
    let at = |i: usize, j: usize| m[3 * i + j];
    let tr = at(0, 0) + at(1, 1) + at(2, 2);
    let cands = [at(0, 0), at(1, 1), at(2, 2), tr];
    let mut c = 0;
    for (k, &v) in cands.iter().enumerate() {
        if v > cands[c] {
            c = k; // strictly greater: the first maximum wins, as numpy's argmax
        }
    }
    let mut q = [0.0; 4];
    if c == 3 {
        q = [at(2, 1) - at(1, 2), at(0, 2) - at(2, 0), at(1, 0) - at(0, 1), 1.0 + tr];
    } else {
        let (i, j) = (c, (c + 1) % 3);
        let k = (j + 1) % 3;
        q[i] = 1.0 - tr + 2.0 * at(i, i);
        q[j] = at(j, i) + at(i, j);
        q[k] = at(k, i) + at(i, k);
        q[3] = at(k, j) - at(j, k);
    }
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}

// ------------------------------------------------------------------------------------------------
// Scripted expert
// ------------------------------------------------------------------------------------------------

/// Meta-World's `SawyerReachV3Policy`: move the hand towards the goal with gain 5 (not clipped:
/// the environment clips), gripper effort 0. Computed in f64, stored as f32 as metaworld 3.x does.
/// `hand` is obs[0..3]; `goal` is the true goal (ML1 observations hide it).
///
/// LEGACY DIFFERENCE: the 2021 policy returned f64 actions.
pub fn expert_action(hand: [f64; 3], goal: [f64; 3]) -> [f32; ACT_DIM] {
    [
        (5.0 * (goal[0] - hand[0])) as f32,
        (5.0 * (goal[1] - hand[1])) as f32,
        (5.0 * (goal[2] - hand[2])) as f32,
        0.0,
    ]
}

/// The scripted expert for data collection: [`expert_action`] plus, optionally, Meta-World's
/// test-harness noise `a ~ N(a, (pct * 2)^2)` on every dimension (2 = the action range), drawn from
/// its own ChaCha8 stream (Meta-World used the global numpy RNG; the noise values differ, the
/// model is the same). The noisy action is rounded to f32, the dataset's type.
#[derive(Debug, Clone)]
pub struct ScriptedExpert {
    std: f64,
    rng: ChaCha8Rng,
}

impl ScriptedExpert {
    /// `noise_pct = 0` is the deterministic expert (every episode of a task is then identical).
    pub fn new(noise_pct: f64, seed: u64) -> Result<Self, EnvError> {
        if !(noise_pct.is_finite() && noise_pct >= 0.0) {
            return Err(EnvError::BadState {
                env: ENV_NAME.into(),
                message: format!("expert noise {noise_pct} is not a finite number >= 0"),
            });
        }
        Ok(Self { std: noise_pct * 2.0, rng: ChaCha8Rng::seed_from_u64(seed) })
    }

    /// The action for `env`'s current state.
    pub fn act(&mut self, env: &MetaWorldReach) -> [f32; ACT_DIM] {
        let mut a = env.expert_action();
        if self.std > 0.0 {
            for v in &mut a {
                *v = (f64::from(*v) + self.std * crate::mujoco_env::standard_normal(&mut self.rng))
                    as f32;
            }
        }
        a
    }
}

// ------------------------------------------------------------------------------------------------
// The family
// ------------------------------------------------------------------------------------------------

/// Meta-World reach: the 50 tasks of `ML1('reach-v2', seed=1)`'s train list (the 2021 code's list,
/// [`TaskList::Legacy`]), goal hidden in the observation as in ML1.
///
/// Task index mapping: task `i` is `ML1('reach-v2', seed=1).train_tasks[i]`, and the paper's split
/// indices 1..20 are used as they are. This is what Prompt-DT's `gen_env` does for Meta-World
/// (`ml1.train_tasks[int(suffix)]` with seed 1; its released pick-place split also indexes
/// `train_tasks` directly). That the paper's reach tasks were built this way is an assumption: no
/// reach configuration was released (spec §4.2 a).
#[derive(Debug, Clone)]
pub struct MetaWorldReachFamily {
    tasks: Vec<[f64; 6]>,
}

impl Default for MetaWorldReachFamily {
    fn default() -> Self {
        Self { tasks: ml1_tasks(1, TaskList::Legacy) }
    }
}

impl MetaWorldReachFamily {
    /// The task vector (object xyz | goal xyz) of `task`.
    pub fn task_vector(&self, task: usize) -> Result<[f64; 6], EnvError> {
        self.tasks.get(task).copied().ok_or(EnvError::UnknownTask {
            env: ENV_NAME.into(),
            task,
            n: self.tasks.len(),
        })
    }

    /// The environment of `task`, as a concrete type (for the expert and full-precision steps).
    pub fn make_env(&self, task: usize) -> Result<MetaWorldReach, EnvError> {
        MetaWorldReach::new(self.task_vector(task)?, false)
    }
}

impl EnvFamily for MetaWorldReachFamily {
    fn name(&self) -> &str {
        ENV_NAME
    }

    fn num_tasks(&self) -> usize {
        self.tasks.len()
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

    /// `default`: the paper's train [1-5, 7, 8, 10-14, 17-19], test [6, 9, 15, 16, 20].
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        match name {
            "default" => Ok((TRAIN_TASKS.to_vec(), TEST_TASKS.to_vec())),
            other => Err(EnvError::unknown_split(ENV_NAME, other, &["default"])),
        }
    }

    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        let v = self.task_vector(task)?;
        Ok(serde_json::json!({
            "obj_init_pos": [v[0], v[1], v[2]],
            "goal": [v[3], v[4], v[5]],
            "source": format!("ML1('reach-v2', seed=1).train_tasks[{task}]"),
        }))
    }

    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(self.make_env(task)?))
    }

    /// Meta-World's action space (the hand's motion is clipped to it).
    /// Frame skip 5 x MuJoCo timestep 0.0025 s (Meta-World's own `render_fps`: 80).
    fn render_fps(&self) -> u32 {
        80
    }

    fn action_bounds(&self) -> ActionBounds {
        ActionBounds::symmetric(1.0, ACT_DIM)
    }

    /// [`SUCCESS_REWARD`].
    fn success_reward(&self) -> Option<f32> {
        Some(SUCCESS_REWARD)
    }

    /// Its scripted policies (`collect.rs`).
    fn scripted(&self) -> Option<ScriptedFamily> {
        Some(ScriptedFamily::new(&collect::ReachPolicies))
    }

    /// From the task's reset state (a reach task has no start-state noise: no `init`).
    fn replay(
        &self,
        task: usize,
        init: Option<&str>,
        actions: &[Vec<f32>],
    ) -> Result<ReplayResult, EnvError> {
        replay_from_reset(&mut self.make_env(task)?, ENV_NAME, task, init, actions)
    }
}

/// Replays `actions` on task `task` of Meta-World reach (goal hidden, as the family's tasks are)
/// from its reset state: a reach task has no start-state noise, so there is no initial state to
/// give. The observations are the f32 ones the datasets and the evaluation see.
pub fn replay_reach(task: usize, actions: &[Vec<f32>]) -> Result<ReplayResult, EnvError> {
    let mut env = MetaWorldReachFamily::default().make_env(task)?;
    replay_from_reset(&mut env, ENV_NAME, task, None, actions)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compiled_model_matches_the_spec() {
        let model = load_model().unwrap_or_else(|e| panic!("{e}"));
        let m = model.ffi();
        let sizes = [m.nq, m.nv, m.nu, m.nmocap, m.neq, m.nbody, m.ngeom, m.nsite, m.nmesh];
        assert_eq!(sizes, [16, 15, 2, 1, 1, 34, 37, 8, 14]);
        assert_eq!(model.opt().timestep, 0.0025);
        let eq = model.eq_data()[0];
        assert_eq!(eq[..11], WELD_EQ_DATA);
        // The 12th number (MuJoCo 3.17's addition) stays as compiled.
        assert_eq!(eq[11], 1.0);
    }

    #[test]
    fn mt19937_matches_the_reference_generator() {
        // init_genrand(5489): the reference implementation's first outputs.
        let mut rng = NumpyRandomState::new(5489);
        let first: Vec<u32> = (0..3).map(|_| rng.next_u32()).collect();
        assert_eq!(first, vec![3_499_211_612, 581_869_302, 3_890_346_734]);
        // np.random.RandomState(0).random_sample() = 0.5488135039273248.
        assert_eq!(NumpyRandomState::new(0).next_f64(), 0.5488135039273248);
    }

    #[test]
    fn tolerance_is_one_inside_and_a_tenth_at_the_margin() {
        assert_eq!(tolerance_long_tail(0.0, 0.3), 1.0);
        assert_eq!(tolerance_long_tail(0.05, 0.3), 1.0);
        let at_margin = tolerance_long_tail(0.05 + 0.3, 0.3);
        assert!((at_margin - 0.1).abs() < 1e-15, "{at_margin}");
        assert!(tolerance_long_tail(0.06, 0.3) < 1.0);
    }

    #[test]
    fn quaternion_branches() {
        let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        assert_eq!(quat_from_matrix(&identity), [0.0, 0.0, 0.0, 1.0]);
        // 180 degrees about x: diag (1, -1, -1), trace -1, branch i = 0.
        let rx = [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0];
        assert_eq!(quat_from_matrix(&rx), [1.0, 0.0, 0.0, 0.0]);
        // 180 degrees about z: branch i = 2.
        let rz = [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0];
        assert_eq!(quat_from_matrix(&rz), [0.0, 0.0, 1.0, 0.0]);
    }
}
