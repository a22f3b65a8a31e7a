//! The MuJoCo families' rules: rewards as the formulas say with the stale torso position, resets,
//! truncation and termination, the contact-cost option, errors, and the vectorised wrapper.

use pdt_envs::ant_dir::{self, AntDirFamily, ContactCost};
use pdt_envs::cheetah::{self, CheetahDirFamily, CheetahVelFamily};
use pdt_envs::mujoco_env::MujocoEnv;
use pdt_envs::replay::replay;
use pdt_envs::vec_env::VecEnv;
use pdt_envs::{family, Env, EnvError};

fn ok<T>(r: Result<T, EnvError>) -> T {
    r.unwrap_or_else(|e| panic!("{e}"))
}

/// A deterministic action sequence in [-1, 1] (no RNG needed).
fn action(t: usize, n: usize) -> Vec<f32> {
    (0..n).map(|i| ((t * 7 + i * 3) as f32 * 0.37).sin()).collect()
}

#[test]
fn registry_knows_the_mujoco_families() {
    for (name, tasks, obs, act) in
        [("cheetah_dir", 2, 20, 6), ("cheetah_vel", 40, 20, 6), ("ant_dir", 50, 27, 8)]
    {
        let fam = ok(family(name));
        assert_eq!((fam.name(), fam.num_tasks()), (name, tasks));
        let p = fam.preset();
        assert_eq!((p.obs_dim, p.act_dim, p.horizon, p.prompt_length), (obs, act, 200, 5));
        let env = ok(fam.make(tasks - 1));
        assert_eq!((env.obs_dim(), env.act_dim(), env.horizon()), (obs, act, 200));
        assert!(matches!(fam.make(tasks), Err(EnvError::UnknownTask { .. })));
    }
    assert!(matches!(family("hopper_vel"), Err(EnvError::UnknownEnv(..))));
}

#[test]
fn cheetah_rewards_use_fresh_qpos_and_the_task_parameter() {
    for (task, direction) in [(0usize, 1.0), (1, -1.0)] {
        let mut env = ok(CheetahDirFamily::default().make_env(task));
        env.reset(5);
        for t in 0..20 {
            let a = action(t, 6);
            let x0 = env.qpos()[0];
            let r = ok(env.step(&a));
            let x1 = env.qpos()[0];
            let want = cheetah::dir_reward(direction, x0, x1, 0.05, &a) as f32;
            assert_eq!(r.reward, want, "task {task} step {t}");
            assert!(!r.terminated && !r.truncated);
            assert_eq!(r.obs.len(), 20);
        }
    }
    let mut env = ok(CheetahVelFamily::default().make_env(7));
    env.reset(1);
    let a = action(0, 6);
    let x0 = env.qpos()[0];
    let r = ok(env.step(&a));
    assert_eq!(r.reward, cheetah::vel_reward(0.6, x0, env.qpos()[0], 0.05, &a) as f32);
}

#[test]
fn cheetah_observation_layout() {
    let mut env = ok(CheetahVelFamily::default().make_env(0));
    env.reset(9);
    let r = ok(env.step(&action(1, 6)));
    let (q, v) = (env.qpos().to_vec(), env.qvel().to_vec());
    let want: Vec<f32> =
        q[1..].iter().chain(&v).chain(&env.torso_xpos()).map(|&x| x as f32).collect();
    assert_eq!(r.obs, want);
    // The torso x in the observation is one 0.01 s sub-step behind qpos[0] (pitfall 22), which is
    // what the reward check undoes.
    assert!((f64::from(r.obs[17]) - (q[0] - 0.01 * v[0])).abs() < 1e-6);
    assert!((cheetah::root_x_from_obs(&r.obs, false) - q[0]).abs() < 1e-5);
}

#[test]
fn ant_reward_reads_the_stale_torso_xpos() {
    let goal = ant_dir::GOALS[3];
    let mut env = ok(AntDirFamily::default().make_env(3));
    env.reset(2);
    let mut differs = false;
    for t in 0..30 {
        let a = action(t, 8);
        let p0 = env.torso_xpos();
        let q0 = env.qpos().to_vec();
        let r = ok(env.step(&a));
        let p1 = env.torso_xpos();
        let want = ant_dir::reward(goal, p0, p1, 0.05, &a, 0.0) as f32;
        assert_eq!(r.reward, want, "step {t}");
        // Recomputing from qpos (fresh positions) would give a different reward.
        let q1 = env.qpos();
        let fresh =
            ant_dir::reward(goal, [q0[0], q0[1], q0[2]], [q1[0], q1[1], q1[2]], 0.05, &a, 0.0)
                as f32;
        differs |= (fresh - r.reward).abs() > 1e-3;
        let (q, v) = (env.qpos(), env.qvel());
        let obs: Vec<f32> = q[2..].iter().chain(v).map(|&x| x as f32).collect();
        assert_eq!(r.obs, obs);
        if r.terminated {
            break;
        }
    }
    assert!(differs, "stale and fresh torso positions never differed");
}

#[test]
fn resets_are_deterministic_per_seed_and_bounded() {
    for fam in [family("cheetah_vel"), family("ant_dir")] {
        let fam = ok(fam);
        let mut a = ok(fam.make(0));
        let mut b = ok(fam.make(0));
        let o1 = a.reset(42);
        let o2 = b.reset(42);
        assert_eq!(o1, o2);
        let o3 = a.reset(43);
        assert_ne!(o1, o3);
        // Episodes depend only on (seed, actions), not on what the env did before.
        for t in 0..10 {
            ok(a.step(&action(t, a.act_dim())));
        }
        assert_eq!(a.reset(42), o2);
        assert_eq!(ok(a.step(&action(0, a.act_dim()))), ok(b.step(&action(0, b.act_dim()))));
    }
    let mut env = ok(AntDirFamily::default().make_env(0));
    for seed in 0..20 {
        env.reset(seed);
        for (q, q0) in env.qpos().iter().zip(env.init_qpos()) {
            assert!((q - q0).abs() <= 0.1);
        }
        assert!(env.qvel().iter().all(|v| v.abs() < 1.0)); // 0.1 N(0,1): |v| < 10 sigma
    }
}

#[test]
fn cheetah_is_truncated_at_200_and_never_terminates() {
    let mut env = ok(CheetahDirFamily::default().make_env(1));
    env.reset(0);
    for t in 0..200 {
        let r = ok(env.step(&action(t, 6)));
        assert!(!r.terminated);
        assert_eq!(r.truncated, t == 199, "step {t}");
    }
    assert!(matches!(env.step(&action(0, 6)), Err(EnvError::Finished { .. })));
    env.reset(1);
    assert!(env.step(&action(0, 6)).is_ok());
}

#[test]
fn ant_terminates_outside_the_healthy_height() {
    let mut env = ok(AntDirFamily::default().make_env(0));
    let mut qpos = env.init_qpos().to_vec();
    qpos[2] = 1.5; // in the air: it falls only ~1 cm in 0.05 s, so z stays above 1.0
    ok(env.reset_to(&qpos, &[0.0; 14]));
    let r = ok(env.step(&[0.0; 8]));
    assert!(r.terminated && !r.truncated);
    assert!(matches!(env.step(&[0.0; 8]), Err(EnvError::Finished { .. })));
    // From the default pose (z = 0.75) standing still is healthy.
    ok(env.reset_to(env.init_qpos().to_vec().as_slice(), &[0.0; 14]));
    assert!(!ok(env.step(&[0.0; 8])).terminated);
}

#[test]
fn contact_cost_option() {
    let run = |cost: ContactCost| -> Vec<(Vec<f32>, f32)> {
        let mut env = ok(AntDirFamily::with_contact_cost(cost).make_env(5));
        env.reset(3);
        (0..40).map(|t| ok(env.step(&action(t, 8)))).map(|r| (r.obs, r.reward)).collect()
    };
    let reference = run(ContactCost::Reference);
    let computed = run(ContactCost::Computed);
    let mut max_cost = 0.0f32;
    for ((o1, r1), (o2, r2)) in reference.iter().zip(&computed) {
        // mj_rnePostConstraint changes no state: the trajectories are identical.
        assert_eq!(o1, o2);
        let cost = r1 - r2;
        assert!(cost >= -1e-6, "contact cost must not be negative: {cost}");
        max_cost = max_cost.max(cost);
    }
    // The ant stands on the floor, so the computed term is positive at least sometimes (it is at
    // most 0.5e-3 * 14 bodies * 6 = 0.042).
    assert!(max_cost > 1e-5 && max_cost <= 0.043, "max contact cost {max_cost}");
    assert_eq!(AntDirFamily::default().contact_cost, ContactCost::Reference);
}

#[test]
fn bad_actions_are_errors_and_change_nothing() {
    let mut env: MujocoEnv = ok(CheetahVelFamily::default().make_env(3));
    env.reset(4);
    let before = (env.qpos().to_vec(), env.qvel().to_vec());
    assert!(matches!(env.step(&[0.0; 5]), Err(EnvError::ActionDim { got: 5, expected: 6, .. })));
    assert!(matches!(env.step(&[0.0; 8]), Err(EnvError::ActionDim { got: 8, expected: 6, .. })));
    let e = env.step(&[0.0, 0.0, f32::NAN, 0.0, 0.0, 0.0]);
    assert!(matches!(e, Err(EnvError::NonFiniteAction { index: 2, .. })), "{e:?}");
    let e = env.step(&[0.0, 0.0, 0.0, 0.0, 0.0, f32::NEG_INFINITY]);
    assert!(matches!(e, Err(EnvError::NonFiniteAction { index: 5, .. })), "{e:?}");
    assert_eq!((env.qpos().to_vec(), env.qvel().to_vec()), before);
    assert_eq!(env.steps(), 0);
    let mut ant = ok(AntDirFamily::default().make_env(0));
    assert!(matches!(ant.step(&[0.0; 6]), Err(EnvError::ActionDim { got: 6, expected: 8, .. })));
    assert!(matches!(
        ant.step(&[f32::INFINITY; 8]),
        Err(EnvError::NonFiniteAction { index: 0, .. })
    ));
}

#[test]
fn replay_errors() {
    let acts = vec![vec![0.0f32; 6]; 3];
    let q = vec![0.0; 9];
    assert!(matches!(replay("point_robot", 0, &q, &q, &acts), Err(EnvError::UnknownEnv(..))));
    assert!(matches!(replay("nope", 0, &q, &q, &acts), Err(EnvError::UnknownEnv(..))));
    assert!(matches!(replay("cheetah_vel", 40, &q, &q, &acts), Err(EnvError::UnknownTask { .. })));
    assert!(matches!(replay("cheetah_vel", 0, &q[..8], &q, &acts), Err(EnvError::BadState { .. })));
    assert!(matches!(replay("ant_dir", 0, &q, &q, &acts), Err(EnvError::BadState { .. })));
    let mut nan = q.clone();
    nan[4] = f64::NAN;
    assert!(matches!(replay("cheetah_dir", 0, &q, &nan, &acts), Err(EnvError::BadState { .. })));
    let mut bad = acts.clone();
    bad[2][1] = f32::NAN;
    match replay("cheetah_dir", 0, &q, &q, &bad) {
        Err(EnvError::NonFiniteAction { env, index: 1, .. }) => {
            assert!(env.contains("step 2"), "{env}")
        }
        other => panic!("{other:?}"),
    }
    let ok_run = ok(replay("cheetah_dir", 0, &q, &q, &vec![vec![0.1f32; 6]; 205]));
    assert_eq!(
        (ok_run.observations.len(), ok_run.rewards.len(), ok_run.unused_actions),
        (201, 200, 5)
    );
    assert_eq!(ok_run.truncated.last(), Some(&true));
}

#[test]
fn vec_env_results_do_not_depend_on_the_thread_count() {
    let make = || -> Vec<Box<dyn Env>> {
        let mut envs = Vec::new();
        for (name, task) in [
            ("cheetah_dir", 0),
            ("cheetah_vel", 12),
            ("ant_dir", 7),
            ("cheetah_vel", 3),
            ("ant_dir", 41),
        ] {
            envs.push(ok(ok(family(name)).make(task)));
        }
        envs
    };
    let run = |threads: usize| {
        let mut venv = VecEnv::new(make(), threads);
        let mut trace = vec![ok(venv.reset(&[1, 2, 3, 4, 5]))];
        for t in 0..30 {
            let acts: Vec<Vec<f32>> = venv.dims().iter().map(|d| action(t, d.act_dim)).collect();
            let steps = ok(venv.step(&acts));
            trace.push(steps.into_iter().map(|s| ok(s).obs).collect());
        }
        trace
    };
    let one = run(1);
    assert_eq!(one, run(2));
    assert_eq!(one, run(3));
    assert_eq!(one, run(8));
    // The same as stepping each environment alone.
    let mut alone = ok(ok(family("ant_dir")).make(7));
    assert_eq!(alone.reset(3), one[0][2]);
    let mut venv = VecEnv::new(make(), 2);
    assert!(venv.reset(&[1, 2]).is_err());
    ok(venv.reset(&[0; 5]));
    let mut acts: Vec<Vec<f32>> = venv.dims().iter().map(|d| vec![0.0; d.act_dim]).collect();
    acts[1] = vec![0.0; 3];
    let out = ok(venv.step(&acts));
    assert!(matches!(out[1], Err(EnvError::ActionDim { .. })));
    assert!(out[0].is_ok() && out[4].is_ok());
}
