//! Environment throughput benchmark: environment steps per second of the MuJoCo families (task 0),
//! one environment on one thread ([`BenchMode::Single`]) and a [`VecEnv`] of several environments
//! stepped together on a given number of threads ([`BenchMode::Vec`]).
//!
//! What is timed, per run, is exactly what an RL loop would need: `step` with a random action, and
//! a `reset` whenever the episode ends (Ant-Dir terminates when it falls; every family truncates at
//! its horizon, 200 steps). What is not timed: building the environments, the first reset, and
//! drawing the actions. Actions are uniform in [-1, 1], drawn before the clock starts from
//! `ChaCha8Rng::seed_from_u64(seed)`; a pool of at most [`ACTION_POOL_STEPS`] steps' actions per
//! environment is drawn and cycled, so memory stays bounded for long runs. Every run of a family
//! uses the same seeds and actions, so the simulated trajectories (and so the work) are the same
//! for every thread count.
//!
//! `scripts/bench/bench_env_gym.py` measures gymnasium's `HalfCheetah-v5` / `Ant-v5` (and a plain
//! Python `mujoco` loop) the same way, for comparison.

use std::hint::black_box;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::ant_dir::{AntDirFamily, ContactCost};
use crate::vec_env::VecEnv;
use crate::{family, Env, EnvError, EnvFamily, StepResult};
use pdt_base::threads::available_cores;

/// At most this many steps' worth of actions are drawn per environment; longer runs cycle them.
pub const ACTION_POOL_STEPS: usize = 4096;

/// Bench-only family name: Ant-Dir with the contact cost computed (`ContactCost::Computed`, which
/// calls `mj_rnePostConstraint` after every step, as gymnasium's `Ant-v5` does by default).
pub const ANT_DIR_CONTACT: &str = "ant_dir_contact";

/// What to measure.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvBenchConfig {
    /// Family names as [`crate::family`] knows them (`cheetah_vel`, `ant_dir`, ...), or
    /// [`ANT_DIR_CONTACT`]. Task 0 of each is stepped.
    pub families: Vec<String>,
    /// Steps taken by each environment, in every mode (a `vec` run takes
    /// `vec_envs * steps_per_env` environment steps in all).
    pub steps_per_env: usize,
    /// Number of environments in the [`VecEnv`] of the `vec` runs.
    pub vec_envs: usize,
    /// One `vec` run per entry, with that many worker threads (empty: no `vec` runs).
    pub threads: Vec<usize>,
    /// Seeds the actions and the environments' resets.
    pub seed: u64,
}

impl Default for EnvBenchConfig {
    /// HalfCheetah-Vel and Ant-Dir, 20,000 steps per environment, 16 environments on 1 thread and
    /// on all the machine's cores.
    fn default() -> Self {
        let cores = available_cores();
        let mut threads = vec![1];
        if cores > 1 {
            threads.push(cores);
        }
        Self {
            families: vec!["cheetah_vel".into(), "ant_dir".into()],
            steps_per_env: 20_000,
            vec_envs: 16,
            threads,
            seed: 0,
        }
    }
}

/// How the environments were stepped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BenchMode {
    /// One environment stepped in a loop on the calling thread.
    Single,
    /// A [`VecEnv`] of several environments stepped together on worker threads.
    Vec,
}

impl BenchMode {
    pub fn as_str(self) -> &'static str {
        match self {
            BenchMode::Single => "single",
            BenchMode::Vec => "vec",
        }
    }
}

impl std::fmt::Display for BenchMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvBenchResult {
    pub family: String,
    pub mode: BenchMode,
    /// Worker threads actually used (`single`: 1; `vec`: the requested count, at most `envs`).
    pub threads: usize,
    /// Environments stepped (`single`: 1).
    pub envs: usize,
    /// Environment steps taken in all (`envs * steps_per_env`).
    pub steps: usize,
    /// Episode resets done inside the timed region (included in `seconds`).
    pub resets: usize,
    /// Wall-clock seconds of the timed region.
    pub seconds: f64,
    /// `steps / seconds`: total environment steps per second over all environments and threads.
    pub steps_per_s: f64,
}

/// Runs the benchmark: for each family, one `single` run, then one `vec` run per entry of
/// `cfg.threads`, in that order.
///
/// Errors: an unknown family name (`UnknownEnv`, before anything is run), a zero `steps_per_env`,
/// a zero `vec_envs` with `vec` runs requested, or an environment error while stepping.
pub fn run(cfg: &EnvBenchConfig) -> Result<Vec<EnvBenchResult>, EnvError> {
    if cfg.steps_per_env == 0 {
        return Err(config_error("steps_per_env must be at least 1"));
    }
    if cfg.vec_envs == 0 && !cfg.threads.is_empty() {
        return Err(config_error("vec_envs must be at least 1 when threads are given"));
    }
    let families =
        cfg.families.iter().map(|name| bench_family(name)).collect::<Result<Vec<_>, _>>()?;
    let mut results = Vec::with_capacity(cfg.families.len() * (1 + cfg.threads.len()));
    for (name, fam) in cfg.families.iter().zip(&families) {
        results.push(run_single(name, fam.as_ref(), cfg.steps_per_env, cfg.seed)?);
        for &threads in &cfg.threads {
            results.push(run_vec(
                name,
                fam.as_ref(),
                cfg.vec_envs,
                threads,
                cfg.steps_per_env,
                cfg.seed,
            )?);
        }
    }
    Ok(results)
}

/// The 1-minute load average from `/proc/loadavg` (Linux), to record how busy the machine was.
pub fn load_avg_1m() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/loadavg").ok()?;
    text.split_whitespace().next()?.parse().ok()
}

fn config_error(message: &str) -> EnvError {
    EnvError::Simulation { env: "env bench".into(), message: message.into() }
}

/// A family by name, accepting the bench-only [`ANT_DIR_CONTACT`] too.
fn bench_family(name: &str) -> Result<Box<dyn EnvFamily>, EnvError> {
    if name == ANT_DIR_CONTACT {
        return Ok(Box::new(AntDirFamily::with_contact_cost(ContactCost::Computed)));
    }
    family(name).map_err(|e| match e {
        EnvError::UnknownEnv(name, _) => EnvError::UnknownEnv(
            name,
            format!("{}, {ANT_DIR_CONTACT}", crate::FAMILY_NAMES.join(", ")),
        ),
        other => other,
    })
}

/// Seed of environment `env`'s episode `episode` (distinct for every pair, any base seed).
fn episode_seed(seed: u64, env: usize, episode: u64) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add((env as u64) << 40).wrapping_add(episode)
}

/// `rows * act_dim` uniform values in [-1, 1], row-major.
fn random_actions(rng: &mut ChaCha8Rng, rows: usize, act_dim: usize) -> Vec<f32> {
    (0..rows * act_dim).map(|_| rng.random_range(-1.0f32..=1.0)).collect()
}

fn rate(steps: usize, seconds: f64) -> f64 {
    if seconds > 0.0 {
        steps as f64 / seconds
    } else {
        f64::INFINITY
    }
}

fn run_single(
    name: &str,
    fam: &dyn EnvFamily,
    steps: usize,
    seed: u64,
) -> Result<EnvBenchResult, EnvError> {
    let mut env = fam.make(0)?;
    let act_dim = env.act_dim();
    let rows = steps.min(ACTION_POOL_STEPS);
    let actions = random_actions(&mut ChaCha8Rng::seed_from_u64(seed), rows, act_dim);
    let mut episode = 0u64;
    env.reset(episode_seed(seed, 0, episode));
    let mut resets = 0usize;

    let start = Instant::now();
    for t in 0..steps {
        let row = t % rows;
        let r = env.step(&actions[row * act_dim..(row + 1) * act_dim])?;
        if r.terminated || r.truncated {
            episode += 1;
            black_box(env.reset(episode_seed(seed, 0, episode)));
            resets += 1;
        }
        black_box(r);
    }
    let seconds = start.elapsed().as_secs_f64();

    Ok(EnvBenchResult {
        family: name.into(),
        mode: BenchMode::Single,
        threads: 1,
        envs: 1,
        steps,
        resets,
        seconds,
        steps_per_s: rate(steps, seconds),
    })
}

fn run_vec(
    name: &str,
    fam: &dyn EnvFamily,
    n: usize,
    threads: usize,
    steps_per_env: usize,
    seed: u64,
) -> Result<EnvBenchResult, EnvError> {
    let resets = Arc::new(AtomicUsize::new(0));
    let mut envs: Vec<Box<dyn Env>> = Vec::with_capacity(n);
    for i in 0..n {
        envs.push(Box::new(AutoReset {
            inner: fam.make(0)?,
            seed,
            index: i,
            episode: 0,
            resets: Arc::clone(&resets),
        }));
    }
    let act_dim = envs[0].act_dim();
    let rows = steps_per_env.min(ACTION_POOL_STEPS);
    // One row per step, `n * act_dim` values: environment `i`'s action at `i * act_dim`, the flat
    // layout `VecEnv::step_flat` takes.
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let actions: Vec<Vec<f32>> = (0..rows).map(|_| random_actions(&mut rng, n, act_dim)).collect();
    let mut venv = VecEnv::new(envs, threads);
    let seeds: Vec<u64> = (0..n).map(|i| episode_seed(seed, i, 0)).collect();
    venv.reset(&seeds)?;

    let start = Instant::now();
    for t in 0..steps_per_env {
        for r in venv.step_flat(&actions[t % rows], None)?.into_iter().flatten() {
            black_box(r?);
        }
    }
    let seconds = start.elapsed().as_secs_f64();

    let steps = n * steps_per_env;
    Ok(EnvBenchResult {
        family: name.into(),
        mode: BenchMode::Vec,
        threads: venv.threads(),
        envs: n,
        steps,
        resets: resets.load(Ordering::Relaxed),
        seconds,
        steps_per_s: rate(steps, seconds),
    })
}

/// Resets its environment as soon as an episode ends, inside `step` (so on the worker thread,
/// inside the timed region), with the next seed of its own sequence; counts the resets.
struct AutoReset {
    inner: Box<dyn Env>,
    seed: u64,
    index: usize,
    episode: u64,
    resets: Arc<AtomicUsize>,
}

impl Env for AutoReset {
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }

    fn act_dim(&self) -> usize {
        self.inner.act_dim()
    }

    fn horizon(&self) -> usize {
        self.inner.horizon()
    }

    fn reset(&mut self, seed: u64) -> Vec<f32> {
        self.inner.reset(seed)
    }

    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError> {
        let r = self.inner.step(action)?;
        if r.terminated || r.truncated {
            self.episode += 1;
            black_box(self.inner.reset(episode_seed(self.seed, self.index, self.episode)));
            self.resets.fetch_add(1, Ordering::Relaxed);
        }
        Ok(r)
    }
}
