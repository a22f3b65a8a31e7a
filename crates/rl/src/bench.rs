//! Update speed of SAC / TD3 (`promptdt bench --cases sac_h256_b256,...`), timed the way
//! `scripts/bench/bench_rl_torch.py` times PyTorch: one iteration = sample a batch from a filled
//! replay buffer of 10,000 transitions and do one update (SAC), or one policy-delay cycle of two
//! updates, the second with the actor and target updates (TD3, whose single updates alternate
//! between two costs). Agent input 20, action 6 (HalfCheetah).

use crate::agent::{Agent, AgentConfig, Algorithm};
use crate::buffer::{ReplayBuffer, Transition};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Device;

pub const OBS: usize = 20;
pub const ACT: usize = 6;
const BUFFER: usize = 10_000;

/// A case name `sac_h256_b256` as (algorithm, hidden units, batch), or `None`.
pub fn parse_case(name: &str) -> Option<(Algorithm, i64, usize)> {
    let mut parts = name.split('_');
    let alg = parts.next()?.parse().ok()?;
    let h = parts.next()?.strip_prefix('h')?.parse().ok().filter(|&h| h > 0)?;
    let b = parts.next()?.strip_prefix('b')?.parse().ok().filter(|&b| b > 0)?;
    parts.next().is_none().then_some((alg, h, b))
}

/// Milliseconds of each of `iters` timed updates (after `warmup` untimed ones).
pub fn time_updates(
    alg: Algorithm,
    hidden: i64,
    batch: usize,
    warmup: usize,
    iters: usize,
    device: Device,
) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut cfg = AgentConfig::default();
    cfg.sac.hidden = vec![hidden, hidden];
    cfg.td3.hidden = vec![hidden, hidden];
    let mut agent = Agent::new(alg, OBS, ACT, &cfg, &mut rng, device);
    let mut buf = ReplayBuffer::new(OBS, ACT, BUFFER);
    let normals = crate::agent::normals(&mut rng, BUFFER * (2 * OBS + 1));
    let (obs, rest) = normals.split_at(BUFFER * OBS);
    let (next, rew) = rest.split_at(BUFFER * OBS);
    for i in 0..BUFFER {
        let act: Vec<f32> = (0..ACT).map(|_| rng.random_range(-1.0..1.0)).collect();
        buf.push(Transition {
            obs: &obs[i * OBS..(i + 1) * OBS],
            action: &act,
            reward: rew[i],
            next_obs: &next[i * OBS..(i + 1) * OBS],
            terminated: false,
        });
    }
    let per_iter = match alg {
        Algorithm::Sac => 1,
        Algorithm::Td3 => cfg.td3.policy_delay.max(1),
    };
    let mut step = |rng: &mut ChaCha8Rng| {
        for _ in 0..per_iter {
            let b = buf.sample(batch, rng, device);
            agent.update(&b, rng);
        }
    };
    for _ in 0..warmup {
        step(&mut rng);
    }
    (0..iters)
        .map(|_| {
            let t = std::time::Instant::now();
            step(&mut rng);
            if let Device::Cuda(_) = device {
                tch::Cuda::synchronize(0);
            }
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect()
}
