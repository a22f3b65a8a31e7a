//! Ant-Dir (`ant_dir`), as the reference defines it (`promptdt-reference.md` e.3;
//! `tp_envs/ant_dir.py` of PEARL/MACAW/Prompt-DT): gym's ant with marker sites, RK4, frame skip 5
//! (dt 0.05 s), 200-step episodes.
//!
//! - Observation (27, f32): `qpos[2:15]` (torso z, quaternion, 8 joint angles) ‖ `qvel[0:14]`.
//! - Action (8): motor commands in [-1, 1] (MuJoCo clamps; the reward uses the raw action).
//! - Reward: `((p_after - p_before)[:2] / dt) . (cos g, sin g) - 0.5 ||a||^2 - contact + 1`, with
//!   `p = xpos(torso)` read as `mj_step` leaves it (never recomputed from `qpos`: with RK4 that
//!   would differ), and `contact` per [`ContactCost`].
//! - Terminated when the state (`qpos` ‖ `qvel`) is not finite or the torso height `qpos[2]` leaves
//!   [0.2, 1.0].

use crate::mujoco_env::{action_sq_norm, Body, MujocoEnv, MujocoTask, StepState, HORIZON};
use crate::replay::{replay_mujoco_init, ReplayResult};
use crate::{
    numeric_param, ActionBounds, BodySymmetry, DatasetBar, Env, EnvError, EnvFamily, EnvPreset,
};

/// Family name, as used in file names (`ant_dir-3-prompt-expert.pkl`).
pub const ENV_NAME: &str = "ant_dir";
/// Number of tasks.
pub const NUM_TASKS: usize = 50;
/// Weight of `||a||^2`.
pub const CTRL_COST_WEIGHT: f64 = 0.5;
/// Weight of `||clip(cfrc_ext, -1, 1)||^2` in the contact cost (`0.5 * 1e-3`).
pub const CONTACT_COST_WEIGHT: f64 = 0.5e-3;
/// Reward for every step survived.
pub const SURVIVE_REWARD: f64 = 1.0;
/// The torso height `qpos[2]` must stay within this range, or the episode terminates.
pub const HEALTHY_Z: (f64, f64) = (0.2, 1.0);
/// Test tasks of the `default` split (the reference's `config/ant_dir/ant_dir_50.json`, = MACAW's).
pub const DEFAULT_TEST_TASKS: [usize; 5] = [6, 17, 23, 30, 41];
/// Train tasks of the `ood` split (paper section 6.4; the reference's `ant_dir_10.json`).
pub const OOD_TRAIN_TASKS: [usize; 8] = [8, 13, 16, 20, 22, 26, 32, 37];
/// Test tasks of the `ood` split.
pub const OOD_TEST_TASKS: [usize; 3] = [1, 4, 41];
/// Split names, the default first.
pub const SPLIT_NAMES: [&str; 3] = ["default", "ood", "ood-paper"];

/// The `ood-paper` split: the paper's text (section 6.4: "the task index is proportional to the
/// desired direction angle") applied to the reference's OOD indices. The stored goals are unsorted
/// random angles (pitfall 17), so here an index is a rank in the tasks ordered by goal angle: the
/// training tasks are those of angle ranks [8, 13, 16, 20, 22, 26, 32, 37] (one arc of goals,
/// 42.7 to 279.7 degrees, with no test goal inside it), the test tasks those of ranks [1, 4, 41]:
/// two below the smallest training angle (14.1 and 21.6 degrees) and one above the largest (298.5).
/// A choice of ours (the paper names no tasks): it keeps the reference's index list and makes every
/// test goal lie outside the training goals' range, which the reference's split does for one of
/// three. The task numbers are computed from [`GOALS`] (a test pins them).
pub fn ood_paper_split() -> (Vec<usize>, Vec<usize>) {
    let mut by_angle: Vec<usize> = (0..NUM_TASKS).collect();
    by_angle.sort_by(|&a, &b| GOALS[a].total_cmp(&GOALS[b]));
    let pick = |ranks: &[usize]| ranks.iter().map(|&r| by_angle[r]).collect::<Vec<_>>();
    (pick(&OOD_TRAIN_TASKS), pick(&OOD_TEST_TASKS))
}

/// Goal directions of the 50 tasks, radians in [0, 2 pi): fixed random draws.
///
/// Provenance: the reference's `config/ant_dir/config_ant_dir_task{i}.pkl` = `[{'goal': g_i}]`, as
/// unpickled into `../shared/data/official-task-parameters.json` (key `ant_dir_goal_radians`),
/// with all digits (a test checks them against the file).
pub const GOALS: [f64; NUM_TASKS] = [
    1.2033605945679715,
    0.42663053293975295,
    4.944775479235424,
    4.123865140631488,
    4.005661927041337,
    3.6166196447991155,
    0.2454395410534735,
    2.2482091824000023,
    5.941902704664186,
    0.3772718531319245,
    5.428936649786095,
    5.512178944021152,
    0.32165928764709933,
    4.099267058824251,
    3.4667560926228758,
    3.754286493596681,
    3.0380999478653634,
    1.7780670544024204,
    1.87066585880318,
    3.5280645037970855,
    2.488439431116824,
    4.9555527108165744,
    2.629414941289294,
    0.9041750006610754,
    0.9481747251390378,
    0.3470916400248258,
    4.511560745487209,
    1.8366841068540096,
    1.2489330732603883,
    5.223613581580657,
    3.5687934580622827,
    0.5173559024487111,
    3.42432703215533,
    0.9987672483128179,
    4.252223478300645,
    0.7443831939965014,
    2.795992744398332,
    5.579358183330077,
    5.009380886994954,
    0.42712294662677097,
    6.036807514750099,
    4.141909635790574,
    4.516203325267859,
    4.672030605450681,
    5.577812002817041,
    0.8416054504725834,
    4.881875268913003,
    5.26525595696687,
    5.210675507763471,
    0.1831988121347493,
];

/// How the contact cost term of the reward is computed.
///
/// The reference computes `0.5e-3 * ||clip(cfrc_ext, -1, 1)||^2` but never calls
/// `mj_rnePostConstraint`, which is what fills `cfrc_ext` under MuJoCo >= 2.0; so in the reference
/// (and in the data recorded with it) the term is always 0 (pitfall 19; openai/gym#1541, #1711).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ContactCost {
    /// As the reference under MuJoCo >= 2: always 0. The default.
    #[default]
    Reference,
    /// What the formula means: call `mj_rnePostConstraint` after stepping (as gymnasium's `step`
    /// does; it changes no state) and charge the clipped external contact forces.
    Computed,
}

/// Ant-Dir's contact cost from `cfrc_ext` (one 6-vector per body): `0.5e-3 ||clip(f, -1, 1)||^2`.
pub fn contact_cost(cfrc_ext: &[[f64; 6]]) -> f64 {
    let sq: f64 = cfrc_ext.iter().flatten().map(|&f| f.clamp(-1.0, 1.0).powi(2)).sum();
    CONTACT_COST_WEIGHT * sq
}

/// Ant-Dir reward: `((p_after - p_before)[:2] / dt) . (cos goal, sin goal) - 0.5 ||a||^2
/// - contact + 1`, with `p` the torso's `xpos` before and after the step.
pub fn reward(
    goal: f64,
    p_before: [f64; 3],
    p_after: [f64; 3],
    dt: f64,
    action: &[f32],
    contact: f64,
) -> f64 {
    let vx = (p_after[0] - p_before[0]) / dt;
    let vy = (p_after[1] - p_before[1]) / dt;
    let forward = vx * goal.cos() + vy * goal.sin();
    forward - CTRL_COST_WEIGHT * action_sq_norm(action) - contact + SURVIVE_REWARD
}

/// Termination: the state is not finite, or the torso height `qpos[2]` is outside [0.2, 1.0].
pub fn is_terminal(qpos: &[f64], qvel: &[f64]) -> bool {
    let finite = qpos.iter().chain(qvel).all(|v| v.is_finite());
    let z = qpos.get(2).copied().unwrap_or(f64::NAN);
    !(finite && z >= HEALTHY_Z.0 && z <= HEALTHY_Z.1)
}

/// An Ant-Dir task: walk in the direction at angle `goal` (radians) in the x-y plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AntDirTask {
    pub goal: f64,
    pub contact_cost: ContactCost,
}

impl MujocoTask for AntDirTask {
    fn body(&self) -> Body {
        Body::Ant
    }

    fn env_name(&self) -> &'static str {
        ENV_NAME
    }

    fn reward(&self, s: &mut StepState<'_>, action: &[f32]) -> (f64, bool) {
        let contact = match self.contact_cost {
            ContactCost::Reference => 0.0,
            ContactCost::Computed => contact_cost(s.contact_forces()),
        };
        let r = reward(self.goal, s.torso_before, s.torso_after, s.dt, action, contact);
        (r, is_terminal(s.qpos(), s.qvel()))
    }
}

/// The 50-task Ant-Dir family. `default()` uses [`ContactCost::Reference`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AntDirFamily {
    pub contact_cost: ContactCost,
}

impl AntDirFamily {
    pub fn with_contact_cost(contact_cost: ContactCost) -> Self {
        Self { contact_cost }
    }

    /// The environment of `task`, as a concrete type (for state access and replay).
    pub fn make_env(&self, task: usize) -> Result<MujocoEnv, EnvError> {
        EnvError::check_task(ENV_NAME, task, NUM_TASKS)?;
        MujocoEnv::new(Box::new(AntDirTask { goal: GOALS[task], contact_cost: self.contact_cost }))
    }
}

impl EnvFamily for AntDirFamily {
    fn name(&self) -> &str {
        ENV_NAME
    }

    fn num_tasks(&self) -> usize {
        NUM_TASKS
    }

    /// `promptdt-reference.md` c.4 (code = paper).
    fn preset(&self) -> EnvPreset {
        EnvPreset {
            obs_dim: Body::Ant.obs_dim(),
            act_dim: Body::Ant.act_dim(),
            horizon: HORIZON,
            rtg_scale: 500.0,
            target_return: 500.0,
            prompt_length: 5,
        }
    }

    fn split_names(&self) -> Vec<String> {
        SPLIT_NAMES.iter().map(|s| (*s).to_owned()).collect()
    }

    /// `default`: test [6, 17, 23, 30, 41], train the other 45. `ood`: train
    /// [8, 13, 16, 20, 22, 26, 32, 37], test [1, 4, 41] (only task 1's goal lies outside the
    /// training goals' range: pitfall 17). `ood-paper`: the same ranks in the tasks ordered by
    /// angle ([`ood_paper_split`]).
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        match name {
            "default" => {
                let train = (0..NUM_TASKS).filter(|t| !DEFAULT_TEST_TASKS.contains(t)).collect();
                Ok((train, DEFAULT_TEST_TASKS.to_vec()))
            }
            "ood" => Ok((OOD_TRAIN_TASKS.to_vec(), OOD_TEST_TASKS.to_vec())),
            "ood-paper" => Ok(ood_paper_split()),
            other => Err(EnvError::unknown_split(ENV_NAME, other, &SPLIT_NAMES)),
        }
    }

    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        EnvError::check_task(ENV_NAME, task, NUM_TASKS)?;
        let contact = match self.contact_cost {
            ContactCost::Reference => "reference",
            ContactCost::Computed => "computed",
        };
        Ok(serde_json::json!({ "goal": GOALS[task], "contact_cost": contact }))
    }

    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(self.make_env(task)?))
    }

    /// MuJoCo clamps the controls to [-1, 1].
    /// Frame skip 5 x MuJoCo timestep 0.01 s (gymnasium's Ant: 20).
    fn render_fps(&self) -> u32 {
        20
    }

    fn action_bounds(&self) -> ActionBounds {
        ActionBounds::symmetric(1.0, Body::Ant.act_dim())
    }

    fn rl_preset(&self) -> Option<&'static str> {
        Some(include_str!("../../../configs/collect/ant_dir.toml"))
    }

    /// `[cos goal, sin goal]` (in f32).
    fn task_features(&self, task: usize) -> Result<Vec<f32>, EnvError> {
        let g = numeric_param(ENV_NAME, task, &self.task_params(task)?, "goal")?;
        Ok(vec![g.cos(), g.sin()])
    }

    /// The reflections across the x and y axes and the half turn ([`Symmetry`]).
    fn symmetries(&self) -> Vec<BodySymmetry> {
        Symmetry::ALL
            .iter()
            .map(|s| BodySymmetry {
                name: s.name(),
                observation: s.observation(),
                action: s.action(),
                task_feature_sign: s.direction_signs().to_vec(),
            })
            .collect()
    }

    fn dataset_bar(&self) -> Option<DatasetBar> {
        Some(DatasetBar::Mean {
            min: 450.0,
            name: "mean expert return over the tasks ≥ 450 (the paper's target return is 500)",
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
    fn reward_follows_the_formula() {
        let a = [1.0f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0];
        // goal pi/2: only y counts; vy = 0.1 / 0.05 = 2; control cost 0.5 * 2 = 1.
        let r =
            reward(std::f64::consts::FRAC_PI_2, [0.0, 0.0, 0.5], [0.3, 0.1, 0.6], 0.05, &a, 0.25);
        assert!((r - (2.0 - 1.0 - 0.25 + 1.0)).abs() < 1e-12, "{r}");
    }

    #[test]
    fn contact_cost_clips_each_component() {
        let f = [[2.0, -3.0, 0.5, 0.0, 0.0, 0.0], [0.0; 6]];
        assert!((contact_cost(&f) - 0.5e-3 * (1.0 + 1.0 + 0.25)).abs() < 1e-15);
    }

    #[test]
    fn termination_rule() {
        let mut q = vec![0.0; 15];
        let v = vec![0.0; 14];
        for (z, done) in [(0.55, false), (0.2, false), (1.0, false), (0.19, true), (1.01, true)] {
            q[2] = z;
            assert_eq!(is_terminal(&q, &v), done, "z = {z}");
        }
        q[2] = 0.5;
        let mut bad = v.clone();
        bad[3] = f64::INFINITY;
        assert!(is_terminal(&q, &bad));
        q[7] = f64::NAN;
        assert!(is_terminal(&q, &v));
    }

    #[test]
    fn splits() {
        let fam = AntDirFamily::default();
        let (train, test) = fam.split("default").unwrap_or_default();
        assert_eq!(test, vec![6, 17, 23, 30, 41]);
        assert_eq!(train.len(), 45);
        let (train, test) = fam.split("ood").unwrap_or_default();
        assert_eq!((train.len(), test), (8, vec![1, 4, 41]));
        // The paper-faithful split: two test goals below every training goal, one above.
        let (train, test) = fam.split("ood-paper").unwrap_or_default();
        assert_eq!(train, vec![35, 0, 27, 22, 16, 30, 41, 46]);
        assert_eq!(test, vec![6, 9, 48]);
        let angle = |t: &usize| GOALS[*t];
        let lo = train.iter().map(angle).fold(f64::INFINITY, f64::min);
        let hi = train.iter().map(angle).fold(f64::NEG_INFINITY, f64::max);
        let below = test.iter().filter(|t| angle(t) < lo).count();
        let above = test.iter().filter(|t| angle(t) > hi).count();
        assert_eq!((below, above), (2, 1));
        // The reference's split has one test goal outside the training range (pitfall 17).
        let (train, test) = fam.split("ood").unwrap_or_default();
        let lo = train.iter().map(angle).fold(f64::INFINITY, f64::min);
        let hi = train.iter().map(angle).fold(f64::NEG_INFINITY, f64::max);
        assert_eq!(test.iter().filter(|t| angle(t) < lo || angle(t) > hi).count(), 1);
        assert_eq!(fam.contact_cost, ContactCost::Reference);
        let p = fam.preset();
        assert_eq!((p.obs_dim, p.act_dim, p.rtg_scale, p.target_return), (27, 8, 500.0, 500.0));
    }
}

/// A symmetry of the Ant: the body, its legs, joint ranges, actuators and the floor are
/// symmetric under both reflections below (and so under their composition, a half turn), so a
/// state mirrored and stepped with the mirrored action stays the mirror of the original
/// trajectory, and the reward for goal `g` becomes the reward for the mirrored goal. A policy that
/// walks towards `g` therefore walks towards the mirrored goal when it sees mirrored observations
/// and its actions are mirrored back (`pdt-rl` uses this for directions its agent walks poorly
/// towards).
///
/// Derivation (`ant_dir.xml`): the legs sit at (±0.2, ±0.2); hips turn about z (range ±30°);
/// ankle axes are (-1, 1, 0) for legs 1 and 3, (1, 1, 0) for legs 2 and 4. A symmetry `S` maps
/// a hinge about axis `n` by angle `φ` to a hinge about `det(S) S n` by `φ`, a free body's
/// rotation `R` to `S R S⁻¹` (a rotation about `det(S) S n`: quaternion `(w, v)` to
/// `(w, det(S) S v)`), linear velocity `v` to `S v`, and the (body-frame) angular velocity `ω` to
/// `det(S) S ω`; `det(S) = -1` for the reflections, +1 for the half turn. Checked by
/// stepping a mirrored state with mirrored actions (`tests/it/ant_symmetry.rs`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Symmetry {
    /// `y -> -y`: legs 1 <-> 4, 2 <-> 3; hip angles change sign, ankles keep it; goal `g -> -g`.
    AcrossX,
    /// `x -> -x`: legs 1 <-> 2, 3 <-> 4; hip and ankle angles change sign; goal `g -> pi - g`.
    AcrossY,
    /// Both, i.e. a half turn about z: legs 1 <-> 3, 2 <-> 4; ankle angles change sign; goal
    /// `g -> g + pi`.
    HalfTurn,
}

/// A signed permutation: `out[i] = sign[i] * x[index[i]]`.
#[derive(Debug, Clone, PartialEq)]
pub struct SignedPerm {
    pub index: Vec<usize>,
    pub sign: Vec<f64>,
}

impl SignedPerm {
    pub fn apply<T: Copy + Into<f64>>(&self, x: &[T]) -> Vec<f64> {
        self.index.iter().zip(&self.sign).map(|(&i, &s)| s * x[i].into()).collect()
    }
}

/// Actuator `k` drives joint `ACTUATOR_JOINT[k]` (joints in `qpos` order: hip_1, ankle_1, ..., hip_4,
/// ankle_4; the XML lists the motors from leg 4).
const ACTUATOR_JOINT: [usize; 8] = [6, 7, 0, 1, 2, 3, 4, 5];

impl Symmetry {
    pub const ALL: [Symmetry; 3] = [Symmetry::AcrossX, Symmetry::AcrossY, Symmetry::HalfTurn];

    pub fn name(self) -> &'static str {
        match self {
            Symmetry::AcrossX => "across_x",
            Symmetry::AcrossY => "across_y",
            Symmetry::HalfTurn => "half_turn",
        }
    }

    /// Leg (0-based) that leg `l` becomes.
    fn leg(self, l: usize) -> usize {
        match self {
            Symmetry::AcrossX => 3 - l,
            Symmetry::AcrossY => [1, 0, 3, 2][l],
            Symmetry::HalfTurn => (l + 2) % 4,
        }
    }

    /// Sign of (hip, ankle) angles.
    fn joint_signs(self) -> (f64, f64) {
        match self {
            Symmetry::AcrossX => (-1.0, 1.0),
            Symmetry::AcrossY => (-1.0, -1.0),
            Symmetry::HalfTurn => (1.0, -1.0),
        }
    }

    /// The 8 leg joints, in `qpos` order.
    fn joints(self) -> SignedPerm {
        let (hip, ankle) = self.joint_signs();
        let mut p = SignedPerm { index: vec![], sign: vec![] };
        for j in 0..8 {
            p.index.push(2 * self.leg(j / 2) + j % 2);
            p.sign.push(if j % 2 == 0 { hip } else { ankle });
        }
        p
    }

    /// Signs of a vector `S v` (position, linear velocity).
    fn vector_signs(self) -> [f64; 3] {
        match self {
            Symmetry::AcrossX => [1.0, -1.0, 1.0],
            Symmetry::AcrossY => [-1.0, 1.0, 1.0],
            Symmetry::HalfTurn => [-1.0, -1.0, 1.0],
        }
    }

    /// Signs of the quaternion's vector part and of the angular velocity: `det(S) S` applied to
    /// an axis (`-S` for a reflection, `S` for the half turn).
    fn axial_signs(self) -> [f64; 3] {
        let v = self.vector_signs();
        let det = v[0] * v[1] * v[2];
        [det * v[0], det * v[1], det * v[2]]
    }

    /// The map of `qpos` (15: position, quaternion, 8 joints).
    pub fn qpos(self) -> SignedPerm {
        let (v, a) = (self.vector_signs(), self.axial_signs());
        let mut p = SignedPerm { index: (0..7).collect(), sign: vec![] };
        p.sign.extend(v);
        p.sign.push(1.0);
        p.sign.extend(a);
        let j = self.joints();
        p.index.extend(j.index.iter().map(|i| i + 7));
        p.sign.extend(j.sign);
        p
    }

    /// The map of `qvel` (14: linear velocity, angular velocity, 8 joints).
    pub fn qvel(self) -> SignedPerm {
        let (v, a) = (self.vector_signs(), self.axial_signs());
        let mut p = SignedPerm { index: (0..6).collect(), sign: vec![] };
        p.sign.extend(v);
        p.sign.extend(a);
        let j = self.joints();
        p.index.extend(j.index.iter().map(|i| i + 6));
        p.sign.extend(j.sign);
        p
    }

    /// The map of the observation (27: `qpos[2:15]` ‖ `qvel`).
    pub fn observation(self) -> SignedPerm {
        let (q, v) = (self.qpos(), self.qvel());
        let mut p = SignedPerm { index: vec![], sign: vec![] };
        for i in 2..15 {
            p.index.push(q.index[i] - 2);
            p.sign.push(q.sign[i]);
        }
        for i in 0..14 {
            p.index.push(v.index[i] + 13);
            p.sign.push(v.sign[i]);
        }
        p
    }

    /// The map of the action (8 motor commands, in actuator order).
    pub fn action(self) -> SignedPerm {
        let j = self.joints();
        let mut p = SignedPerm { index: vec![], sign: vec![] };
        for &joint in &ACTUATOR_JOINT {
            let src = j.index[joint];
            let k = ACTUATOR_JOINT.iter().position(|&x| x == src).unwrap_or(0);
            p.index.push(k);
            p.sign.push(j.sign[joint]);
        }
        p
    }

    /// The mirrored goal direction (radians).
    pub fn goal(self, g: f64) -> f64 {
        match self {
            Symmetry::AcrossX => -g,
            Symmetry::AcrossY => std::f64::consts::PI - g,
            Symmetry::HalfTurn => g + std::f64::consts::PI,
        }
    }

    /// Signs of the goal's `(cos g, sin g)` under the symmetry.
    pub fn direction_signs(self) -> [f64; 2] {
        let v = self.vector_signs();
        [v[0], v[1]]
    }
}
