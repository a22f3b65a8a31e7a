//! Env steps/s of `metaworld_reach`, one environment on one thread, measured the way
//! `scripts/metaworld/replay.py bench` measures the Python twin and metaworld 3.1.1: task 1 of the
//! family, uniform random actions in [-1, 1] drawn before the clock starts, a reset every 500 steps
//! (included in the time). Usage: `cargo run --release -p pdt-envs --example metaworld_reach_bench
//! [STEPS]` (default 20000).

use std::hint::black_box;
use std::time::Instant;

use pdt_envs::metaworld_reach::{MetaWorldReachFamily, HORIZON};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let steps: usize = match std::env::args().nth(1) {
        Some(s) => s.parse()?,
        None => 20_000,
    };
    let mut env = MetaWorldReachFamily::default().make_env(1)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let actions: Vec<[f32; 4]> =
        (0..steps).map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0))).collect();
    env.reset_f64();
    let start = Instant::now();
    for a in &actions {
        let s = env.step_f64(a)?;
        if s.truncated {
            black_box(env.reset_f64());
        }
        black_box(s);
    }
    let secs = start.elapsed().as_secs_f64();
    println!(
        "rust metaworld_reach: {steps} steps (random actions, reset every {HORIZON}) in {secs:.2} s \
         = {:.0} steps/s",
        steps as f64 / secs
    );
    Ok(())
}
