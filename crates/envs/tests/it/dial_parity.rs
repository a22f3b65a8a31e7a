//! Rust vs Python for `dial`: the fixtures in `testdata/dial/` were written by
//! `scripts/dial/twin.py fixtures` (a raw-`mujoco==3.17.0` twin of the reconstructed environment).
//! Replaying their actions through the Rust environment must give the same observations and
//! rewards bit for bit, the same success (terminated) and truncation flags, and on the noiseless
//! expert cases the same expert actions. Cases: the noiseless expert on all 10 digits, the noisy
//! expert from two perturbed starts (the reset's settling loop), uniform random actions 1.5 times
//! the action box (truncation at 200 steps), and saturating actions that push into the pad.
//!
//! Every step is checked through a digest (FNV-1a 64 of the 39 observation f64s, the reward f64,
//! the success and truncation bytes); the observations of a few steps are stored in full, so a
//! failure names the first differing value.

use std::collections::BTreeMap;

use serde::Deserialize;

use pdt_envs::dial::{Dial, DialExpert, DialStep, ACT_DIM, HORIZON};
use pdt_envs::{Env, EnvError};

use crate::support;
use support::{base64_decode, fnv1a64};

#[derive(Deserialize)]
struct Fixture {
    mujoco: String,
    cases: Vec<Case>,
}

#[derive(Deserialize)]
struct Case {
    digit: usize,
    policy: String,
    start: Option<Vec<f64>>,
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

fn read(name: &str) -> String {
    let path = format!("{}/../../testdata/dial/{name}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn digest(obs: &[f64], reward: f64, success: bool, truncated: bool) -> String {
    let bytes = obs
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .chain(reward.to_le_bytes())
        .chain([u8::from(success), u8::from(truncated)]);
    format!("{:016x}", fnv1a64(bytes))
}

fn actions(case: &Case) -> Vec<[f32; ACT_DIM]> {
    let bytes = base64_decode(&case.actions_f32_b64);
    assert_eq!(bytes.len() % (4 * ACT_DIM), 0, "actions are 9 f32 per step");
    bytes
        .chunks_exact(4 * ACT_DIM)
        .map(|c| {
            std::array::from_fn(|i| {
                f32::from_le_bytes([c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]])
            })
        })
        .collect()
}

fn first_difference(got: &[f64], want: &[f64]) -> String {
    match got.iter().zip(want).position(|(g, w)| g.to_bits() != w.to_bits()) {
        Some(i) => format!("obs[{i}]: rust {:e}, python {:e}", got[i], want[i]),
        None => "no value differs in the stored observation".into(),
    }
}

fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Replays one case on `env` (reset first); panics at the first difference. Returns the steps.
fn replay_case(env: &mut Dial, c: usize, case: &Case) -> usize {
    let want = &case.expected;
    let obs0 = match &case.start {
        Some(q) => env.reset_from(q).unwrap_or_else(|e| panic!("case {c}: {e}")),
        None => env.reset_f64(),
    };
    if let Some(w) = want.full_observations.get("0") {
        assert!(same_bits(&obs0, w), "case {c}: reset obs {}", first_difference(&obs0, w));
    }
    assert_eq!(digest(&obs0, 0.0, false, false), want.reset_digest, "case {c}: reset observation");
    let acts = actions(case);
    assert_eq!(acts.len(), want.step_digests.len(), "case {c}: fixture lengths");
    let flag = |s: &str, t: usize| s.as_bytes()[t] == b'1';
    let mut expert = DialExpert::new(case.digit).unwrap_or_else(|e| panic!("{e}"));
    let mut obs32: Vec<f32> = obs0.iter().map(|&v| v as f32).collect();
    for (t, a) in acts.iter().enumerate() {
        let where_ = format!("case {c} (digit {}, {}) step {t}", case.digit, case.policy);
        if case.policy == "expert" {
            let e = expert.act(&obs32);
            assert_eq!(
                e.map(f32::to_bits),
                a.map(f32::to_bits),
                "{where_}: expert action {e:?} vs {a:?}"
            );
        }
        let s: DialStep = env.step_f64(a).unwrap_or_else(|e| panic!("{where_}: {e}"));
        assert_eq!(s.reward.to_bits(), want.rewards[t].to_bits(), "{where_}: reward");
        assert_eq!(s.success, flag(&want.success, t), "{where_}: success");
        assert_eq!(s.truncated, flag(&want.truncated, t), "{where_}: truncated");
        if let Some(w) = want.full_observations.get(&(t + 1).to_string()) {
            assert!(same_bits(&s.obs, w), "{where_}: observation {}", first_difference(&s.obs, w));
        }
        assert_eq!(
            digest(&s.obs, s.reward, s.success, s.truncated),
            want.step_digests[t],
            "{where_}: observation digest"
        );
        obs32 = s.obs.iter().map(|&v| v as f32).collect();
    }
    acts.len()
}

#[test]
fn dial_matches_python_bitwise() {
    let fixture: Fixture =
        serde_json::from_str(&read("replay-dial.json")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(fixture.mujoco, "3.17.0");
    let policies: Vec<&str> = fixture.cases.iter().map(|c| c.policy.as_str()).collect();
    for p in ["expert", "noisy_expert", "random", "saturate"] {
        assert!(policies.contains(&p), "the fixture has no {p} case");
    }
    let digits: std::collections::BTreeSet<usize> =
        fixture.cases.iter().filter(|c| c.policy == "expert").map(|c| c.digit).collect();
    assert_eq!(digits.len(), 10, "the noiseless expert on every digit");
    let mut steps = 0;
    for (c, case) in fixture.cases.iter().enumerate() {
        let mut env = Dial::new(case.digit).unwrap_or_else(|e| panic!("case {c}: {e}"));
        let n = replay_case(&mut env, c, case);
        let last = n - 1;
        let ended = case.expected.success.as_bytes()[last] == b'1'
            || case.expected.truncated.as_bytes()[last] == b'1';
        assert!(ended, "case {c}: the fixture's episode ends");
        if case.policy == "expert" {
            assert_eq!(case.expected.rewards[last], 1.0, "case {c}: the expert reaches its digit");
        }
        if case.policy == "random" || case.policy == "saturate" {
            assert_eq!(n, HORIZON, "case {c}: truncation at the horizon");
        }
        // The episode is over: the env refuses another step.
        assert!(matches!(env.step_f64(&[0.0; ACT_DIM]), Err(EnvError::Finished { .. })));
        // A second episode on the same instance is the same: reset leaves nothing behind.
        if c == 0 || case.start.is_some() {
            steps += replay_case(&mut env, c, case);
        }
        steps += n;
    }
    eprintln!("dial: {} cases, {steps} steps, bitwise equal", fixture.cases.len());
}

#[test]
fn bad_input_is_refused_and_changes_nothing() {
    let mut env = Dial::new(3).unwrap_or_else(|e| panic!("{e}"));
    let before = *env.obs_f64();
    assert!(matches!(
        env.step_f64(&[0.0; 8]),
        Err(EnvError::ActionDim { got: 8, expected: 9, .. })
    ));
    let mut nan = [0.0f32; ACT_DIM];
    nan[4] = f32::NAN;
    assert!(matches!(env.step_f64(&nan), Err(EnvError::NonFiniteAction { index: 4, .. })));
    let mut inf = [0.0f32; ACT_DIM];
    inf[0] = f32::INFINITY;
    assert!(matches!(env.step_f64(&inf), Err(EnvError::NonFiniteAction { index: 0, .. })));
    assert_eq!(env.steps(), 0);
    assert_eq!(env.obs_f64().map(f64::to_bits), before.map(f64::to_bits));
    assert!(matches!(env.reset_from(&[0.0; 3]), Err(EnvError::BadState { .. })));
    let mut q = [0.0; 9];
    q[2] = f64::NAN;
    let err = env.reset_from(&q).expect_err("NaN start");
    assert!(err.to_string().contains("qpos[2]"), "{err}");
    q[2] = 1e6;
    assert!(env.reset_from(&q).is_err());
    assert!(matches!(Dial::new(10), Err(EnvError::UnknownTask { task: 10, n: 10, .. })));
    // After all that, the env still steps.
    assert!(env.step(&[0.0; ACT_DIM]).is_ok());
}
