//! Env steps/s of `dial`, one environment on one thread, measured the way `scripts/dial/twin.py
//! bench` measures the Python twin: digit 9, uniform random actions in 1.5 times the action box
//! drawn before the clock starts (random actions never reach the digit, so episodes run to the
//! 200-step horizon), a reset at each episode end (included in the time). Each step is 20 MuJoCo
//! sub-steps. Usage: `cargo run --release -p pdt-envs --example dial_bench [STEPS]` (default 20000).

use std::hint::black_box;
use std::time::Instant;

use pdt_envs::dial::{Dial, ACT_DIM, C_HIGH, C_LOW, HORIZON};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let steps: usize = match std::env::args().nth(1) {
        Some(s) => s.parse()?,
        None => 20_000,
    };
    let mut env = Dial::new(9)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let actions: Vec<[f32; ACT_DIM]> = (0..steps)
        .map(|_| {
            std::array::from_fn(|j| rng.random_range(1.5 * C_LOW[j] as f32..1.5 * C_HIGH[j] as f32))
        })
        .collect();
    env.reset_f64();
    let start = Instant::now();
    for a in &actions {
        let s = env.step_f64(a)?;
        if s.truncated || s.success {
            black_box(env.reset_f64());
        }
        black_box(s);
    }
    let secs = start.elapsed().as_secs_f64();
    println!(
        "rust dial: {steps} steps (random actions, reset every {HORIZON}) in {secs:.2} s = {:.0} \
         steps/s",
        steps as f64 / secs
    );
    Ok(())
}
