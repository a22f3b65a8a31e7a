//! Rust vs Python for `metaworld_reach`: the fixtures in `testdata/metaworld/` were written by
//! `scripts/metaworld/replay.py` (a raw-`mujoco==3.17.0` twin of the environment, checked bit for
//! bit against metaworld 3.1.1 `reach-v3` by `replay.py check`). Replaying their task vectors and
//! actions through the Rust environment must give the same observations and rewards bit for bit,
//! the same success and truncation flags, and (on the expert cases) the same expert actions; the
//! task generator must give numpy's ML1 task lists bit for bit.
//!
//! Every step is checked through a digest (FNV-1a 64 of the 39 observation f64s, the reward f64,
//! the success and truncation bytes) because full 500-step observations would make the fixture
//! large; rewards and the observations of a few steps are stored in full, so a failure names the
//! first differing step and value.

use std::collections::BTreeMap;

use serde::Deserialize;

use pdt_envs::metaworld_reach::{
    ml1_tasks, MetaWorldReach, MetaWorldReachFamily, ReachStep, TaskList, HORIZON,
};
use pdt_envs::{Env, EnvError, EnvFamily};

use crate::support;
use support::{base64_decode, fnv1a64};

#[derive(Deserialize)]
struct Fixture {
    mujoco: String,
    cases: Vec<Case>,
}

#[derive(Deserialize)]
struct Case {
    task: usize,
    goal_visible: bool,
    policy: String,
    rand_vec: [f64; 6],
    actions_f32_b64: String,
    expected: Expected,
}

#[derive(Deserialize)]
struct Expected {
    reset_digest: String,
    step_digests: Vec<String>,
    rewards: Vec<f64>,
    success: String,
    truncated: String,
    full_observations: BTreeMap<String, Vec<f64>>,
}

#[derive(Deserialize)]
struct TaskLists {
    lists: BTreeMap<String, Vec<[f64; 6]>>,
}

fn read(name: &str) -> String {
    let path = format!("{}/../../testdata/metaworld/{name}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn reset_digest(obs: &[f64]) -> String {
    format!("{:016x}", fnv1a64(obs.iter().flat_map(|v| v.to_le_bytes())))
}

fn step_digest(s: &ReachStep) -> String {
    let bytes = s
        .obs
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .chain(s.reward.to_le_bytes())
        .chain([u8::from(s.success), u8::from(s.truncated)]);
    format!("{:016x}", fnv1a64(bytes))
}

fn actions(case: &Case) -> Vec<[f32; 4]> {
    let bytes = base64_decode(&case.actions_f32_b64);
    assert_eq!(bytes.len() % 16, 0, "actions are 4 f32 per step");
    bytes
        .chunks_exact(16)
        .map(|c| {
            let f =
                |i: usize| f32::from_le_bytes([c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]]);
            [f(0), f(1), f(2), f(3)]
        })
        .collect()
}

fn first_difference(got: &[f64], want: &[f64]) -> String {
    match got.iter().zip(want).position(|(g, w)| g.to_bits() != w.to_bits()) {
        Some(i) => format!("obs[{i}]: rust {:e}, python {:e}", got[i], want[i]),
        None => "no value differs in the stored observation".into(),
    }
}

/// Replays one case on `env` (reset first); panics at the first difference.
fn replay_case(env: &mut MetaWorldReach, c: usize, case: &Case) -> usize {
    let want = &case.expected;
    let obs0 = env.reset_f64();
    if let Some(w) = want.full_observations.get("0") {
        assert!(
            obs0.iter().zip(w).all(|(a, b)| a.to_bits() == b.to_bits()),
            "case {c}: reset obs {}",
            first_difference(&obs0, w)
        );
    }
    assert_eq!(reset_digest(&obs0), want.reset_digest, "case {c}: reset observation");
    let acts = actions(case);
    assert_eq!(acts.len(), want.step_digests.len(), "case {c}: fixture lengths");
    let flag = |s: &str, t: usize| s.as_bytes()[t] == b'1';
    for (t, a) in acts.iter().enumerate() {
        if case.policy == "expert" {
            let e = env.expert_action();
            let bits = |x: &[f32; 4]| x.map(f32::to_bits);
            assert_eq!(
                bits(&e),
                bits(a),
                "case {c} step {t}: expert action rust {e:?}, python {a:?}"
            );
        }
        let s = env.step_f64(a).unwrap_or_else(|e| panic!("case {c} step {t}: {e}"));
        let where_ = format!("case {c} (task {}, {}) step {t}", case.task, case.policy);
        assert_eq!(
            s.reward.to_bits(),
            want.rewards[t].to_bits(),
            "{where_}: reward rust {:e}, python {:e}",
            s.reward,
            want.rewards[t]
        );
        assert_eq!(s.success, flag(&want.success, t), "{where_}: success");
        assert_eq!(s.truncated, flag(&want.truncated, t), "{where_}: truncated");
        if let Some(w) = want.full_observations.get(&(t + 1).to_string()) {
            assert!(
                s.obs.iter().zip(w).all(|(a, b)| a.to_bits() == b.to_bits()),
                "{where_}: observation {}",
                first_difference(&s.obs, w)
            );
        }
        assert_eq!(step_digest(&s), want.step_digests[t], "{where_}: observation digest");
    }
    acts.len()
}

#[test]
fn reach_matches_python_bitwise() {
    let fixture: Fixture =
        serde_json::from_str(&read("replay-reach.json")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(fixture.mujoco, "3.17.0");
    let family = MetaWorldReachFamily::default();
    let mut steps = 0;
    let policies: Vec<&str> = fixture.cases.iter().map(|c| c.policy.as_str()).collect();
    for p in ["expert", "expert_noise", "uniform", "saturate"] {
        assert!(policies.contains(&p), "the fixture has no {p} case");
    }
    for (c, case) in fixture.cases.iter().enumerate() {
        // The fixture's tasks are the family's (ML1 reach-v2 seed 1), bit for bit.
        let v = family.task_vector(case.task).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(v.map(f64::to_bits), case.rand_vec.map(f64::to_bits), "case {c}: task vector");
        let mut env = MetaWorldReach::new(case.rand_vec, case.goal_visible)
            .unwrap_or_else(|e| panic!("case {c}: {e}"));
        let n = replay_case(&mut env, c, case);
        assert_eq!(n, HORIZON, "case {c}: full episodes check truncation");
        // The episode is over: Meta-World raises, the Rust env refuses.
        assert!(matches!(env.step_f64(&[0.0; 4]), Err(EnvError::Finished { .. })));
        // A second episode on the same instance is the same: reset leaves nothing behind.
        if c == 2 {
            steps += replay_case(&mut env, c, case);
        }
        steps += n;
    }
    eprintln!("metaworld_reach: {} cases, {steps} steps, bitwise equal", fixture.cases.len());
}

#[test]
fn ml1_task_lists_match_numpy() {
    let lists: TaskLists =
        serde_json::from_str(&read("tasks-reach.json")).unwrap_or_else(|e| panic!("{e}"));
    for (name, seed, list) in [
        ("legacy_seed1", 1, TaskList::Legacy),
        ("legacy_seed2", 2, TaskList::Legacy),
        ("v3_seed1", 1, TaskList::V3),
        ("v3_seed2", 2, TaskList::V3),
    ] {
        let want = &lists.lists[name];
        let got = ml1_tasks(seed, list);
        assert_eq!(got.len(), 50);
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert_eq!(g.map(f64::to_bits), w.map(f64::to_bits), "{name} task {i}: {g:?} vs {w:?}");
        }
    }
}

#[test]
fn env_trait_rounds_the_full_precision_step() {
    let family = MetaWorldReachFamily::default();
    let mut env = family.make_env(1).unwrap_or_else(|e| panic!("{e}"));
    let mut twin = family.make_env(1).unwrap_or_else(|e| panic!("{e}"));
    let first = Env::reset(&mut env, 123);
    assert_eq!(first.len(), 39);
    // Goal hidden (ML1), though the expert knows it.
    assert_eq!(first[36..], [0.0; 3]);
    assert_ne!(twin.goal(), [0.0; 3]);
    let mut ret = 0.0;
    for t in 0..HORIZON {
        let a = twin.expert_action();
        let full = twin.step_f64(&a).unwrap_or_else(|e| panic!("{e}"));
        let r = env.step(&a).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.obs, full.obs.iter().map(|&v| v as f32).collect::<Vec<_>>(), "step {t}");
        assert_eq!(r.reward, full.reward as f32);
        assert_eq!(r.success, Some(full.success));
        assert!(!r.terminated);
        assert_eq!(r.truncated, t + 1 == HORIZON);
        ret += full.reward;
    }
    // The expert solves the task (spec: returns about 4800 of at most 5000).
    assert!(ret > 4700.0 && ret <= 5000.0, "expert return {ret}");
}

#[test]
fn bad_input_is_refused_with_typed_errors() {
    let family = pdt_envs::family("metaworld_reach").unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(family.num_tasks(), 50);
    assert!(matches!(family.make(50), Err(EnvError::UnknownTask { task: 50, n: 50, .. })));
    assert!(matches!(family.task_params(77), Err(EnvError::UnknownTask { task: 77, .. })));
    assert!(matches!(family.split("ood"), Err(EnvError::UnknownSplit { .. })));
    let mut env = family.make(6).unwrap_or_else(|e| panic!("{e}"));
    env.reset(0);
    assert_eq!(
        env.step(&[0.1, 0.2, 0.3]),
        Err(EnvError::ActionDim { env: "metaworld_reach".into(), got: 3, expected: 4 })
    );
    let nan = env.step(&[0.0, f32::NAN, 0.0, 0.0]);
    assert!(matches!(nan, Err(EnvError::NonFiniteAction { index: 1, .. })), "{nan:?}");
    let inf = env.step(&[0.0, 0.0, 0.0, f32::NEG_INFINITY]);
    assert!(matches!(inf, Err(EnvError::NonFiniteAction { index: 3, .. })), "{inf:?}");
    // A refused step changes nothing: the episode still has all its steps, from the reset state.
    let mut fresh = family.make(6).unwrap_or_else(|e| panic!("{e}"));
    fresh.reset(0);
    for t in 0..HORIZON {
        let a = [0.3, -0.2, 0.1, 0.5];
        assert_eq!(env.step(&a), fresh.step(&a), "step {t}");
    }
    assert!(matches!(env.step(&[0.0; 4]), Err(EnvError::Finished { .. })));
    // A task vector that is not finite.
    let bad = MetaWorldReach::new([0.0, 0.6, 0.02, f64::NAN, 0.8, 0.2], false);
    assert!(matches!(bad, Err(EnvError::BadState { .. })));
}

#[test]
fn family_preset_and_split() {
    let family = MetaWorldReachFamily::default();
    let p = family.preset();
    assert_eq!((p.obs_dim, p.act_dim, p.horizon, p.prompt_length), (39, 4, 500, 2));
    assert_eq!((p.rtg_scale, p.target_return), (650.0, 1500.0));
    let (train, test) = family.split("default").unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(train, vec![1, 2, 3, 4, 5, 7, 8, 10, 11, 12, 13, 14, 17, 18, 19]);
    assert_eq!(test, vec![6, 9, 15, 16, 20]);
    // Task 1 of ML1('reach-v2', seed=1) (spec §4.2, full precision).
    let params = family.task_params(1).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(params["goal"][0], 0.034093502035680456);
    assert_eq!(params["obj_init_pos"][1], 0.6878117436390945);
}

#[test]
fn noisy_expert_is_seeded_and_still_succeeds() {
    use pdt_envs::metaworld_reach::ScriptedExpert;
    let family = MetaWorldReachFamily::default();
    let run = |seed: u64| {
        let mut env = family.make_env(18).unwrap_or_else(|e| panic!("{e}"));
        let mut expert = ScriptedExpert::new(0.1, seed).unwrap_or_else(|e| panic!("{e}"));
        let (mut actions, mut ret, mut ever) = (Vec::new(), 0.0, false);
        for _ in 0..HORIZON {
            let a = expert.act(&env);
            let s = env.step_f64(&a).unwrap_or_else(|e| panic!("{e}"));
            actions.push(a);
            ret += s.reward;
            ever |= s.success;
        }
        (actions, ret, ever)
    };
    let (a1, r1, ever) = run(7);
    let (a2, r2, _) = run(7);
    let (a3, _, _) = run(8);
    assert_eq!(a1, a2);
    assert_eq!(r1, r2);
    assert_ne!(a1, a3);
    assert!(ever && r1 > 4500.0, "noisy expert: return {r1}, success {ever}");
    assert!(ScriptedExpert::new(f64::NAN, 0).is_err());
    assert!(ScriptedExpert::new(-0.1, 0).is_err());
}
