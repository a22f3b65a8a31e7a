//! Episodes of an adapted MACAW policy: deterministic mean actions clipped to the action box
//! (the official `sample_mode`), all episodes of a task stepped together with one batched forward
//! per environment step.

use crate::{act, Dims, MacawConfig, MacawError};
use pdt_envs::vec_env::VecEnv;
use pdt_envs::EnvFamily;
use tch::{Device, Kind, Tensor};

/// One finished episode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Episode {
    pub seed: u64,
    pub episode_return: f64,
    pub length: usize,
    /// The policy gave a non-finite action, which ended the episode there (its return so far).
    pub failed: bool,
    /// Whether some step solved the task (families with a success criterion), else `None`.
    pub success: Option<bool>,
}

/// Runs one episode per seed on task `task` of `family` with the policy parameters `policy`,
/// stepping the environments on `threads` threads. The result does not depend on `threads`.
///
/// DIFFERENCE: an adapted policy whose parameters are finite can still overflow on an observation
/// and act NaN. The official code would pass NaN to MuJoCo and log a NaN return; here the episode
/// ends at that step with the return so far and is marked `failed`, so one bad adaptation does not
/// end the run's evaluation.
#[allow(clippy::too_many_arguments)]
pub fn run_episodes(
    family: &dyn EnvFamily,
    task: usize,
    policy: &[Tensor],
    dims: &Dims,
    cfg: &MacawConfig,
    seeds: &[u64],
    threads: usize,
    device: Device,
) -> Result<Vec<Episode>, MacawError> {
    let envs = seeds.iter().map(|_| family.make(task)).collect::<Result<Vec<_>, _>>()?;
    let (o, a) = (dims.obs as usize, dims.act as usize);
    if let Some(e) = envs.iter().find(|e| e.obs_dim() != o || e.act_dim() != a) {
        return Err(MacawError::Config(format!(
            "{} task {task} has obs/act dims {}/{}, the policy {o}/{a}",
            family.name(),
            e.obs_dim(),
            e.act_dim()
        )));
    }
    let kind = policy.first().map_or(Kind::Float, Tensor::kind);
    let mut venv = VecEnv::new(envs, threads);
    let n = seeds.len();
    let mut obs = venv.reset(seeds)?;
    let mut done = vec![false; n];
    let mut returns = vec![0f64; n];
    let mut lengths = vec![0usize; n];
    let mut failed = vec![false; n];
    let mut success: Vec<Option<bool>> = vec![None; n];
    let mut flat = vec![0f32; n * a];
    while done.iter().any(|d| !d) {
        let active: Vec<usize> = (0..n).filter(|&i| !done[i]).collect();
        let x: Vec<f32> = active.iter().flat_map(|&i| obs[i].iter().copied()).collect();
        let x = Tensor::from_slice(&x).view([active.len() as i64, o as i64]);
        let y = act(policy, dims, &x.to_kind(kind).to_device(device), cfg)
            .to_kind(Kind::Float)
            .to_device(Device::Cpu)
            .contiguous()
            .view([-1]);
        let y: Vec<f32> = Vec::<f32>::try_from(&y)?;
        for (k, &i) in active.iter().enumerate() {
            let ai = &y[k * a..(k + 1) * a];
            if ai.iter().all(|v| v.is_finite()) {
                flat[i * a..(i + 1) * a].copy_from_slice(ai);
            } else {
                failed[i] = true;
                done[i] = true;
            }
        }
        let mask: Vec<bool> = done.iter().map(|d| !d).collect();
        if !mask.iter().any(|&m| m) {
            break;
        }
        for (i, slot) in venv.step_flat(&flat, Some(&mask))?.into_iter().enumerate() {
            if let Some(r) = slot {
                let r = r?;
                returns[i] += f64::from(r.reward);
                lengths[i] += 1;
                if let Some(ok) = r.success {
                    success[i] = Some(success[i].unwrap_or(false) || ok);
                }
                done[i] = r.terminated || r.truncated;
                obs[i] = r.obs;
            }
        }
    }
    Ok(seeds
        .iter()
        .enumerate()
        .map(|(i, &seed)| Episode {
            seed,
            episode_return: returns[i],
            length: lengths[i],
            failed: failed[i],
            success: success[i],
        })
        .collect())
}
