//! Rust vs Python: the fixtures in `testdata/mujoco/` were written by `scripts/mujoco/replay.py`
//! (the official Python bindings `mujoco==3.17.0`, environments written from the same description);
//! replaying their initial states and actions through the Rust environments must give the same
//! observations and rewards bit for bit, and the same flags.

use serde::Deserialize;

use pdt_envs::replay::replay;

#[derive(Deserialize)]
struct Fixture {
    family: String,
    mujoco: String,
    cases: Vec<Case>,
}

#[derive(Deserialize)]
struct Case {
    task: usize,
    init_qpos: Vec<f64>,
    init_qvel: Vec<f64>,
    actions: Vec<Vec<f32>>,
    expected: Expected,
}

#[derive(Deserialize)]
struct Expected {
    observations: Vec<Vec<f32>>,
    rewards: Vec<f32>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
    unused_actions: usize,
}

fn check(family: &str) {
    let path = format!("{}/../../testdata/mujoco/replay-{family}.json", env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let fixture: Fixture = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{path}: {e}"));
    assert_eq!(fixture.family, family);
    assert_eq!(fixture.mujoco, "3.17.0");
    let mut steps = 0;
    for (c, case) in fixture.cases.iter().enumerate() {
        let got = replay(family, case.task, &case.init_qpos, &case.init_qvel, &case.actions)
            .unwrap_or_else(|e| panic!("{family} case {c}: {e}"));
        let want = &case.expected;
        assert_eq!(got.observations.len(), want.observations.len(), "{family} case {c}: length");
        for (t, (g, w)) in got.observations.iter().zip(&want.observations).enumerate() {
            let gb: Vec<u32> = g.iter().map(|v| v.to_bits()).collect();
            let wb: Vec<u32> = w.iter().map(|v| v.to_bits()).collect();
            assert_eq!(
                gb, wb,
                "{family} case {c}: observation {t} differs:\n rust   {g:?}\n python {w:?}"
            );
        }
        for (t, (g, w)) in got.rewards.iter().zip(&want.rewards).enumerate() {
            assert_eq!(
                g.to_bits(),
                w.to_bits(),
                "{family} case {c}: reward {t}: rust {g}, python {w}"
            );
        }
        assert_eq!(got.rewards.len(), want.rewards.len());
        assert_eq!(got.terminated, want.terminated, "{family} case {c}");
        assert_eq!(got.truncated, want.truncated, "{family} case {c}");
        assert_eq!(got.unused_actions, want.unused_actions, "{family} case {c}");
        steps += got.rewards.len();
    }
    eprintln!("{family}: {} cases, {steps} steps, bitwise equal", fixture.cases.len());
}

#[test]
fn cheetah_dir_matches_python_bitwise() {
    check("cheetah_dir");
}

#[test]
fn cheetah_vel_matches_python_bitwise() {
    check("cheetah_vel");
}

#[test]
fn ant_dir_matches_python_bitwise() {
    check("ant_dir");
}
