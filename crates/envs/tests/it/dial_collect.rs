//! Dial data collection and the scripted expert: the noiseless expert reaches every digit from the
//! deterministic reset, the noisy expert (DART noise, perturbed starts) succeeds in every episode
//! of every digit, the policies are ordered, the reward fires exactly when the rule says (1 on the
//! step that ends within L1 0.1 of the digit's press point, terminated there; 0 before), and the
//! same configuration gives the same bytes.

use pdt_data::mode::Mode;
use pdt_data::native;
use pdt_envs::collect_scripted::{collect, CollectConfig};
use pdt_envs::dial::{
    run_dial_episode, Dial, DialExpert, DialFamily, ACT_DIM, C_HIGH, C_LOW, HORIZON, NUM_TASKS,
    SUCCESS_L1,
};
use pdt_envs::{Env, EnvFamily};
use rand::{Rng, SeedableRng};

use crate::support;
use support::dir_bytes;

fn config(seed: u64, episodes: usize, modes: Vec<Mode>, tasks: Vec<usize>) -> CollectConfig {
    CollectConfig {
        seed,
        episodes_per_task: episodes,
        prompt_episodes: 2,
        modes,
        tasks,
        ..CollectConfig::for_family(DialFamily.scripted().expect("dial is scripted"))
    }
}

#[test]
fn noiseless_expert_reaches_every_digit() {
    let mut lengths = Vec::new();
    for digit in 0..NUM_TASKS {
        let mut env = Dial::new(digit).expect("env");
        let mut expert = DialExpert::new(digit).expect("expert");
        let mut obs = env.reset(0);
        let mut steps = 0;
        loop {
            let a = expert.act(&obs);
            let s = env.step(&a).expect("step");
            steps += 1;
            obs = s.obs;
            if s.terminated || s.truncated {
                assert!(s.terminated && s.reward == 1.0, "digit {digit}: not reached");
                break;
            }
        }
        lengths.push(steps);
    }
    println!("noiseless expert steps per digit 0..9: {lengths:?}");
    assert!(lengths.iter().all(|&n| n < HORIZON));
}

#[test]
fn noisy_expert_succeeds_on_every_digit_and_policies_are_ordered() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = config(7, 20, Mode::ALL.to_vec(), (0..NUM_TASKS).collect());
    let summary = collect(&cfg, dir.path(), &mut |_, _| {}).expect("collect");
    let card = native::read_card(dir.path()).expect("card").expect("card present");
    assert_eq!((card.env.as_str(), card.obs_dim, card.act_dim), ("dial", 39, 9));
    let mut medium = 0.0;
    for digit in 0..NUM_TASKS {
        let stat = |m: Mode| summary.get(digit, m).expect("collected");
        let (e, m, r) = (stat(Mode::Expert), stat(Mode::Medium), stat(Mode::Random));
        println!(
            "digit {digit}: expert {:?}, medium {:?}, random {:?}",
            e.success_rate, m.success_rate, r.success_rate
        );
        assert_eq!(e.success_rate, Some(1.0), "digit {digit}: the noisy expert failed");
        assert_eq!(e.dataset.mean, 1.0);
        assert_eq!(r.success_rate, Some(0.0), "digit {digit}: random reached the digit");
        medium += m.dataset.mean / NUM_TASKS as f64;
    }
    assert!(medium > 0.2 && medium < 0.9, "medium policy mean return {medium}");
}

#[test]
fn reward_fires_exactly_when_the_rule_says() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    for digit in [0, 3, 7] {
        let mut env = Dial::new(digit).expect("env");
        // Expert episodes (noisy starts, DART noise) and uniformly random ones.
        for _ in 0..3 {
            let (traj, ok) = run_dial_episode(&mut env, Mode::Expert, &mut rng).expect("episode");
            let n = traj.len();
            assert!(ok && traj.rewards[n - 1] == 1.0 && traj.terminated[n - 1]);
            assert!(traj.rewards[..n - 1].iter().all(|&r| r == 0.0));
            assert!(!traj.terminated[..n - 1].iter().any(|&t| t));
        }
        // Step by step: success (and reward 1, terminated) exactly when the end effector ends the
        // step within the radius (the step stops at the sub-step that reaches it).
        let mut expert = DialExpert::new(digit).expect("expert");
        for random in [false, true] {
            let mut obs = env.reset(0);
            loop {
                let a: [f32; ACT_DIM] = if random {
                    std::array::from_fn(|j| rng.random_range(C_LOW[j] as f32..=C_HIGH[j] as f32))
                } else {
                    expert.act(&obs)
                };
                let s = env.step(&a).expect("step");
                let within = env.distance() < SUCCESS_L1;
                assert_eq!(s.success, Some(within));
                assert_eq!(s.reward, if within { 1.0 } else { 0.0 });
                assert_eq!(s.terminated, within);
                obs = s.obs;
                if s.terminated || s.truncated {
                    assert_eq!(s.truncated, !within && env.steps() == HORIZON);
                    break;
                }
            }
        }
    }
}

#[test]
fn same_seed_same_bytes_other_seed_other_data() {
    let (a, b, c) =
        (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let cfg = config(11, 3, vec![Mode::Expert, Mode::Random], vec![2, 9]);
    collect(&cfg, a.path(), &mut |_, _| {}).expect("collect a");
    collect(&cfg, b.path(), &mut |_, _| {}).expect("collect b");
    assert_eq!(dir_bytes(a.path()), dir_bytes(b.path()));
    // A file does not depend on the other tasks in the run.
    let one = config(11, 3, vec![Mode::Expert, Mode::Random], vec![9]);
    collect(&one, c.path(), &mut |_, _| {}).expect("collect c");
    let name = "dial-9-expert.safetensors";
    assert_eq!(dir_bytes(a.path())[name], dir_bytes(c.path())[name]);
    let other = config(12, 3, vec![Mode::Expert, Mode::Random], vec![2, 9]);
    let d = tempfile::tempdir().unwrap();
    collect(&other, d.path(), &mut |_, _| {}).expect("collect d");
    assert_ne!(dir_bytes(a.path())[name], dir_bytes(d.path())[name]);
    // Unknown digits are refused before anything is written.
    let bad = config(11, 3, vec![Mode::Expert], vec![10]);
    let e = tempfile::tempdir().unwrap();
    let err = collect(&bad, e.path(), &mut |_, _| {}).expect_err("digit 10");
    assert!(err.to_string().contains("unknown task 10"), "{err}");
    assert!(dir_bytes(e.path()).is_empty());
}
