//! Episodes of an adapted MACAW policy: deterministic mean actions clipped to the action box
//! (the official `sample_mode`), all episodes of a task stepped together with one batched forward
//! per environment step.

use crate::{act, Dims, MacawError};
use pdt_envs::rollout::{run_batch, BatchPolicy};
use pdt_envs::{EnvError, EnvFamily, StepResult};
use pdt_rundir::config::macaw::MacawConfig;
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

/// The episodes of [`run_episodes`] as the [`run_batch`] loop drives them (slot `i`: seed `i`).
struct Running<'p> {
    policy: &'p [Tensor],
    dims: &'p Dims,
    cfg: &'p MacawConfig,
    kind: Kind,
    device: Device,
    obs: Vec<Vec<f32>>,
    returns: Vec<f64>,
    lengths: Vec<usize>,
    failed: Vec<bool>,
    success: Vec<Option<bool>>,
}

impl BatchPolicy for Running<'_> {
    type Error = MacawError;

    fn act(&mut self, slots: &[usize]) -> Result<Vec<f32>, MacawError> {
        let o = self.dims.obs;
        let x: Vec<f32> = slots.iter().flat_map(|&i| self.obs[i].iter().copied()).collect();
        let x = Tensor::from_slice(&x).view([slots.len() as i64, o]);
        let y = act(self.policy, self.dims, &x.to_kind(self.kind).to_device(self.device), self.cfg)
            .to_kind(Kind::Float)
            .to_device(Device::Cpu)
            .contiguous()
            .view([-1]);
        Ok(Vec::<f32>::try_from(&y)?)
    }

    /// A non-finite action ends the episode there, unstepped (see [`run_episodes`]).
    fn ends_before_step(&mut self, slot: usize, action: &[f32]) -> bool {
        let failed = !action.iter().all(|v| v.is_finite());
        if failed {
            self.failed[slot] = true;
        }
        failed
    }

    fn batch_error(&self, _slots: &[usize], error: EnvError) -> MacawError {
        error.into()
    }

    fn record(
        &mut self,
        slot: usize,
        _action: &[f32],
        step: Result<StepResult, EnvError>,
    ) -> Result<bool, MacawError> {
        let r = step?;
        self.returns[slot] += f64::from(r.reward);
        self.lengths[slot] += 1;
        if let Some(ok) = r.success {
            self.success[slot] = Some(self.success[slot].unwrap_or(false) || ok);
        }
        self.obs[slot] = r.obs;
        Ok(r.terminated || r.truncated)
    }
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
    // Made by the family, wherever its environments live (`EnvFamily::make_batch`).
    let mut venv = family.make_batch(&vec![task; seeds.len()], threads)?;
    let (o, a) = (dims.obs as usize, dims.act as usize);
    if let Some(e) = venv.dims().iter().find(|e| e.obs_dim != o || e.act_dim != a) {
        return Err(MacawError::Config(format!(
            "{} task {task} has obs/act dims {}/{}, the policy {o}/{a}",
            family.name(),
            e.obs_dim,
            e.act_dim
        )));
    }
    let kind = policy.first().map_or(Kind::Float, Tensor::kind);
    let n = seeds.len();
    let obs = venv.reset(seeds)?;
    let mut run = Running {
        policy,
        dims,
        cfg,
        kind,
        device,
        obs,
        returns: vec![0f64; n],
        lengths: vec![0usize; n],
        failed: vec![false; n],
        success: vec![None; n],
    };
    run_batch(&mut venv, (0..n).collect(), &mut run)?;
    let Running { returns, lengths, failed, success, .. } = run;
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
