//! End-to-end learning checks on tiny budgets.
#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use pdt_rl::agent::{Agent, AgentConfig, Algorithm};
use pdt_rl::buffer::{ReplayBuffer, Transition};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::Device;

/// Updates per second of SAC / TD3 at the paper-scale sizes (run with --ignored --nocapture).
#[test]
#[ignore]
fn update_speed() {
    for alg in [Algorithm::Sac, Algorithm::Td3] {
        for (d, a) in [(20usize, 6usize), (29, 8)] {
            let mut rng = ChaCha8Rng::seed_from_u64(0);
            let mut agent = Agent::new(alg, d, a, &AgentConfig::default(), &mut rng, Device::Cpu);
            let mut buf = ReplayBuffer::new(d, a, 10_000);
            let obs = vec![0.1f32; d];
            let act = vec![0.2f32; a];
            for i in 0..10_000 {
                buf.push(Transition {
                    obs: &obs,
                    action: &act,
                    reward: i as f32 * 1e-4,
                    next_obs: &obs,
                    terminated: false,
                });
            }
            for _ in 0..50 {
                let b = buf.sample(256, &mut rng, Device::Cpu);
                agent.update(&b, &mut rng);
            }
            let n = 500;
            let t = std::time::Instant::now();
            for _ in 0..n {
                let b = buf.sample(256, &mut rng, Device::Cpu);
                agent.update(&b, &mut rng);
            }
            let s = t.elapsed().as_secs_f64();
            println!(
                "{alg:?} obs {d} act {a}: {:.0} updates/s ({:.2} ms)",
                n as f64 / s,
                1e3 * s / n as f64
            );
        }
    }
}

use pdt_rl::train::{train, RlConfig, Start};

fn tiny(family: &str, alg: Algorithm, steps: u64) -> RlConfig {
    let mut cfg = RlConfig::preset(family).unwrap();
    cfg.algorithm = alg;
    cfg.total_steps = steps;
    cfg.learning_starts = steps / 4;
    cfg.batch_size = 32;
    cfg.checkpoint_every = steps / 3;
    cfg.agent.sac.hidden = vec![16, 16];
    cfg.agent.td3.hidden = vec![16, 16];
    cfg
}

/// A run stopped after a checkpoint and resumed ends bitwise where the uninterrupted run ends:
/// same episode log, same snapshots, same exported agent.
#[test]
fn interrupted_and_resumed_run_equals_uninterrupted_run() {
    for alg in [Algorithm::Sac, Algorithm::Td3] {
        let tmp = tempfile::tempdir().unwrap();
        let cfg = tiny("cheetah_dir", alg, 900);
        let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
        let full = train(Start::New(&cfg), &a, None, Device::Cpu, &mut |_| {}).unwrap().unwrap();
        let stopped = train(Start::New(&cfg), &b, Some(450), Device::Cpu, &mut |_| {}).unwrap();
        assert!(stopped.is_none(), "stopped early");
        assert!(b.join("checkpoint.safetensors").exists());
        assert!(matches!(
            train(Start::New(&cfg), &b, None, Device::Cpu, &mut |_| {}),
            Err(pdt_rl::RlError::Exists { .. })
        ));
        let resumed = train(
            Start::Resume { total_steps: None, tasks: None, sample_recent: None },
            &b,
            None,
            Device::Cpu,
            &mut |_| {},
        )
        .unwrap()
        .unwrap();
        assert_eq!(full.snapshots, resumed.snapshots, "{alg:?}");
        assert_eq!(full.expert_step, resumed.expert_step);
        for f in ["agent/expert.safetensors", "agent/medium.safetensors", "episodes.csv"] {
            assert!(std::fs::read(a.join(f)).unwrap() == std::fs::read(b.join(f)).unwrap(), "{f}");
        }
    }
}

/// SAC on the point robot (horizon 20, reward -distance to the goal) beats uniform random actions
/// by far within a few thousand steps: the algorithm learns.
#[test]
fn sac_learns_the_point_robot() {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = tiny("point_robot", Algorithm::Sac, 4000);
    cfg.learning_starts = 500;
    cfg.batch_size = 64;
    cfg.agent.sac.hidden = vec![64, 64];
    cfg.tasks = vec![0, 1, 2, 3];
    cfg.snapshot_fractions = vec![1.0];
    let card =
        train(Start::New(&cfg), tmp.path(), None, Device::Cpu, &mut |_| {}).unwrap().unwrap();
    let mean =
        |v: &[f64], tasks: &[usize]| tasks.iter().map(|&t| v[t]).sum::<f64>() / tasks.len() as f64;
    let (random, expert) =
        (mean(&card.random_eval, &cfg.tasks), mean(&card.expert_eval, &cfg.tasks));
    // The scripted expert gets about -4 and uniform random actions about -20 to -24: the trained
    // agent must close at least half of that gap (the margin absorbs CPU-dependent rounding in
    // the matmuls, which changes the learning trajectory from machine to machine).
    let scripted_expert = -4.0;
    assert!(expert > 0.5 * (random + scripted_expert), "random {random:.2}, trained {expert:.2}");
}

#[test]
fn datasets_from_an_agent_are_deterministic_and_described_by_a_card() {
    use pdt_rl::datasets::{generate, DatasetConfig};
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = tiny("ant_dir", Algorithm::Sac, 400);
    cfg.snapshot_fractions = vec![0.5, 1.0];
    train(Start::New(&cfg), &tmp.path().join("run"), None, Device::Cpu, &mut |_| {})
        .unwrap()
        .unwrap();
    let dcfg = DatasetConfig {
        episodes: 2,
        prompt_episodes: 1,
        tasks: vec![0, 17],
        chunk: 3,
        threads: 3,
        ..Default::default()
    };
    let agent = tmp.path().join("run/agent");
    let s1 = generate(&agent, &tmp.path().join("d1"), &dcfg, Device::Cpu, &mut |_, _| {}).unwrap();
    // Another thread count, same bytes.
    let s2 = generate(
        &agent,
        &tmp.path().join("d2"),
        &DatasetConfig { threads: 1, ..dcfg.clone() },
        Device::Cpu,
        &mut |_, _| {},
    )
    .unwrap();
    assert_eq!(s1.files, 2 * 2 * 3);
    for e in &s1.entries {
        let name = format!("ant_dir-{}-{}.safetensors", e.task, e.mode.name());
        let a = std::fs::read(tmp.path().join("d1").join(&name)).unwrap();
        let b = std::fs::read(tmp.path().join("d2").join(&name)).unwrap();
        assert!(a == b, "{name} depends on the thread count");
    }
    assert_eq!(s1.entries, s2.entries);
    let card = pdt_data::native::read_card(&tmp.path().join("d1")).unwrap().unwrap();
    assert_eq!(card.env, "ant_dir");
    assert_eq!(card.tasks.len(), 2);
    assert_eq!(card.tasks[1].files.len(), 6);
    assert_eq!(card.generator["algorithm"], "sac");
    // The data loads back as a multi-task dataset with prompts.
    let ds = pdt_data::native::read_task_dataset(
        &tmp.path().join("d1/ant_dir-17-prompt-expert.safetensors"),
    )
    .unwrap();
    assert_eq!(ds.trajectories.len(), 1);
    assert_eq!(ds.trajectories[0].obs_dim, 27);
}

#[test]
fn bad_inputs_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let e = RlConfig::preset("walker").unwrap_err().to_string();
    assert!(e.contains("walker"), "{e}");
    let mut cfg = tiny("cheetah_vel", Algorithm::Td3, 100);
    cfg.tasks = vec![40];
    let e = train(Start::New(&cfg), tmp.path(), None, Device::Cpu, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("40"), "{e}");
    let e = train(
        Start::Resume { total_steps: None, tasks: None, sample_recent: None },
        &tmp.path().join("none"),
        None,
        Device::Cpu,
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("no checkpoint"), "{e}");
    // A truncated checkpoint names the file.
    let run = tmp.path().join("r");
    let cfg = tiny("cheetah_dir", Algorithm::Sac, 300);
    train(Start::New(&cfg), &run, Some(100), Device::Cpu, &mut |_| {}).unwrap();
    let ck = run.join("checkpoint.safetensors");
    let bytes = std::fs::read(&ck).unwrap();
    std::fs::write(&ck, &bytes[..bytes.len() / 2]).unwrap();
    let e = train(
        Start::Resume { total_steps: None, tasks: None, sample_recent: None },
        &run,
        None,
        Device::Cpu,
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("checkpoint.safetensors") && e.contains("truncated"), "{e}");
    // A policy file that is not one.
    std::fs::write(tmp.path().join("p.safetensors"), b"junk").unwrap();
    let e = pdt_rl::policy::load(&tmp.path().join("p.safetensors"), Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(e.contains("p.safetensors") && e.contains("4 bytes, too short"), "{e}");
}

/// A finished run resumed with a larger budget keeps training and snapshotting on the new
/// schedule, and its expert can come from the extension.
#[test]
fn a_finished_run_can_be_extended() {
    let tmp = tempfile::tempdir().unwrap();
    let mut cfg = tiny("cheetah_dir", Algorithm::Td3, 600);
    cfg.snapshot_fractions = vec![0.5, 1.0];
    let first =
        train(Start::New(&cfg), tmp.path(), None, Device::Cpu, &mut |_| {}).unwrap().unwrap();
    assert_eq!(first.snapshots.iter().map(|s| s.step).collect::<Vec<_>>(), vec![400, 600]);
    let e = train(
        Start::Resume { total_steps: Some(200), tasks: None, sample_recent: None },
        tmp.path(),
        None,
        Device::Cpu,
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("cannot shrink"), "{e}");
    let longer = train(
        Start::Resume { total_steps: Some(1200), tasks: None, sample_recent: None },
        tmp.path(),
        None,
        Device::Cpu,
        &mut |_| {},
    )
    .unwrap()
    .unwrap();
    let steps: Vec<u64> = longer.snapshots.iter().map(|s| s.step).collect();
    assert_eq!(steps, vec![400, 600, 1200], "new schedule: 600 (done), then 1200");
    assert_eq!(longer.config.total_steps, 1200);
}
