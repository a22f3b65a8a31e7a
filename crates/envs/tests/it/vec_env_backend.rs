//! `VecEnv` over a [`Backend`] (`VecEnv::external`, how a Python worker's environments are
//! stepped): the same environments behind a backend in this process give what the thread pool
//! gives, call for call; an action of the wrong size is refused in its slot; a backend that answers
//! out of turn is an error, not a silent mix-up.

use pdt_envs::vec_env::{Backend, EnvDims, StepSlot, VecEnv};
use pdt_envs::{family, Env, EnvError};

fn ok<T>(r: Result<T, EnvError>) -> T {
    r.unwrap_or_else(|e| panic!("{e}"))
}

/// Built-in environments behind the backend interface, stepped in order on the calling thread.
struct InProcess {
    envs: Vec<Box<dyn Env>>,
    /// Answer a reset for environment 0 whether it was asked or not.
    out_of_turn: bool,
}

impl Backend for InProcess {
    fn reset(&mut self, seeds: &[Option<u64>]) -> Result<Vec<Option<Vec<f32>>>, EnvError> {
        let mut out: Vec<Option<Vec<f32>>> =
            self.envs.iter_mut().zip(seeds).map(|(e, s)| s.map(|s| e.reset(s))).collect();
        if self.out_of_turn {
            out[0] = Some(self.envs[0].reset(0));
        }
        Ok(out)
    }

    fn step(&mut self, actions: &[f32], mask: &[bool]) -> Result<Vec<StepSlot>, EnvError> {
        let mut at = 0;
        let mut out = Vec::new();
        for (e, &on) in self.envs.iter_mut().zip(mask) {
            let a = &actions[at..at + e.act_dim()];
            at += e.act_dim();
            out.push(on.then(|| e.step(a)));
        }
        Ok(out)
    }
}

fn mixed() -> Vec<Box<dyn Env>> {
    [("cheetah_vel", 12), ("point_robot", 3), ("ant_dir", 7), ("point_robot", 30)]
        .into_iter()
        .map(|(name, task)| ok(ok(family(name)).make(task)))
        .collect()
}

fn external(out_of_turn: bool) -> VecEnv {
    let envs = mixed();
    let dims = envs
        .iter()
        .map(|e| EnvDims { obs_dim: e.obs_dim(), act_dim: e.act_dim(), horizon: e.horizon() })
        .collect();
    VecEnv::external(Box::new(InProcess { envs, out_of_turn }), dims)
}

#[test]
fn a_backend_steps_as_the_thread_pool_does() {
    let mut pool = VecEnv::new(mixed(), 2);
    let mut ext = external(false);
    assert_eq!(pool.dims(), ext.dims());
    assert_eq!((ext.threads(), ext.flat_action_len()), (1, pool.flat_action_len()));
    assert_eq!(ok(pool.reset(&[1, 2, 3, 4])), ok(ext.reset(&[1, 2, 3, 4])));
    for t in 0..30 {
        if t == 12 {
            assert_eq!(
                ok(pool.reset_some(&[(2, 9), (1, 8)])),
                ok(ext.reset_some(&[(2, 9), (1, 8)]))
            );
        }
        let flat: Vec<f32> =
            (0..pool.flat_action_len()).map(|j| ((t * 5 + j) as f32 * 0.3).sin()).collect();
        let mask: Vec<bool> = (0..4).map(|i| (t + i) % 3 != 0).collect();
        let a = ok(pool.step_flat(&flat, Some(&mask)));
        let b = ok(ext.step_flat(&flat, Some(&mask)));
        assert_eq!(format!("{a:?}"), format!("{b:?}"), "step {t}");
        let each: Vec<Vec<f32>> =
            (0..4).map(|i| flat[pool.action_range(i).expect("range")].to_vec()).collect();
        assert_eq!(format!("{:?}", ok(pool.step(&each))), format!("{:?}", ok(ext.step(&each))));
    }
    // An action of the wrong size is its environment's error only (in fresh episodes: the point
    // robot's have ended by now).
    ok(ext.reset(&[5, 6, 7, 8]));
    let mut each: Vec<Vec<f32>> = ext.dims().iter().map(|d| vec![0.0; d.act_dim]).collect();
    each[1].push(0.0);
    let out = ok(ext.step(&each));
    assert!(matches!(out[1], Err(EnvError::ActionDim { got: 3, expected: 2, .. })), "{:?}", out[1]);
    assert!(out.iter().enumerate().all(|(i, r)| i == 1 || r.is_ok()));
    let size = pdt_envs::render::FrameSize::new(8, 8).expect("size");
    assert!(ext.render(0, size).is_err(), "rendering is refused outside this process");
}

#[test]
fn a_backend_answering_out_of_turn_is_an_error() {
    let mut ext = external(true);
    let e = ext.reset_some(&[(2, 1)]).expect_err("refused").to_string();
    assert!(e.contains("environment 0: answer reset out of turn"), "{e}");
}
