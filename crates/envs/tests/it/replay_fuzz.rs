//! Replay requests from hostile hands (`promptdt env replay`, `pdt_envs::replay`): any state and
//! any actions give an error naming the field, or a replay whose every number is finite.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_envs::replay::{replay, ReplayInput};
use proptest::prelude::*;

/// Values at and around the edges MuJoCo cares about.
fn number() -> impl Strategy<Value = f64> {
    prop_oneof![
        4 => -2.0..2.0f64,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(1e308),
        1 => Just(-1e10),
        1 => Just(1e10 + 1.0),
        1 => Just(9.9e9),
        1 => any::<f64>(),
    ]
}

/// Mostly ordinary values (so most cases reach the simulator), sometimes hostile ones.
fn values(n: usize) -> impl Strategy<Value = Vec<f64>> {
    prop_oneof![
        3 => prop::collection::vec(-1.5..1.5f64, n),
        1 => prop::collection::vec(number(), n),
    ]
}

/// Mostly the right size (so most cases reach the simulator), sometimes one off.
fn size_off() -> impl Strategy<Value = i32> {
    prop_oneof![8 => Just(0), 1 => Just(-1), 1 => Just(1)]
}

fn family() -> impl Strategy<Value = (&'static str, usize, usize, usize)> {
    // (family, nq, nv, act_dim)
    prop_oneof![
        Just(("cheetah_vel", 9, 9, 6)),
        Just(("cheetah_dir", 9, 9, 6)),
        Just(("ant_dir", 15, 14, 8))
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn any_request_is_refused_by_name_or_replayed_finite(
        (fam, nq, nv, na) in family(),
        task in prop_oneof![9 => 0usize..2, 1 => 0usize..60],
        dq in size_off(), dv in size_off(),
        qpos in values(16),
        qvel in values(16),
        actions in prop::collection::vec(values(9), 0..6),
        act_len_off in size_off(),
    ) {
        let qpos = &qpos[..(nq as i32 + dq) as usize];
        let qvel = &qvel[..(nv as i32 + dv) as usize];
        let na = (na as i32 + act_len_off) as usize;
        let actions: Vec<Vec<f32>> =
            actions.iter().map(|a| a[..na].iter().map(|&x| x as f32).collect()).collect();
        match replay(fam, task, qpos, qvel, &actions) {
            Ok(r) => {
                for o in &r.observations {
                    prop_assert!(o.iter().all(|x| x.is_finite()), "{o:?}");
                }
                prop_assert!(r.rewards.iter().all(|x| x.is_finite()), "{:?}", r.rewards);
                prop_assert_eq!(r.observations.len(), r.rewards.len() + 1);
            }
            Err(e) => {
                let m = e.to_string();
                prop_assert!(!m.is_empty());
            }
        }
    }

    /// Random text as a request document never panics the parser.
    #[test]
    fn random_documents_never_panic(text in ".{0,200}") {
        let _ = serde_json::from_str::<ReplayInput>(&text);
    }
}
