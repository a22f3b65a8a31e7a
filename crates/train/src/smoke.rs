//! A tiny end-to-end check that needs no data on disk: two synthetic tasks, one sampled batch, a
//! few training steps. (The full demo, with environments, comes with the evaluation crate.)

use crate::optim::Optimizer;
use crate::step::{train_step, DeviceBatch, StepStats};
use pdt_data::{TaskData, TaskDataset, TaskId, Trajectory};
use pdt_model::{PromptDt, PromptDtConfig};
use pdt_prompt::{BatchSampler, Rng, SamplerConfig, StateNorm};
use pdt_rundir::config::AdamWConfig;
use pdt_rundir::config::LossOn;
use rand::{Rng as _, SeedableRng};
use tch::{nn::VarStore, Device};

/// A task whose optimal action is a fixed direction: a_t = tanh(goal), with noisy states.
fn synthetic_task(index: usize, rng: &mut Rng) -> TaskData {
    let (ds, da, t) = (4, 2, 30);
    let goal = [index as f32 - 0.5, 0.5 - index as f32];
    let make = |rng: &mut Rng, n: usize| {
        let trajs = (0..n)
            .map(|_| {
                let obs: Vec<f32> = (0..t * ds).map(|_| rng.random_range(-1.0..1.0)).collect();
                let act: Vec<f32> = (0..t).flat_map(|_| goal.map(f32::tanh)).collect();
                let rew = vec![1.0; t];
                let mut trunc = vec![false; t];
                trunc[t - 1] = true;
                Trajectory::new(ds, da, obs, act, rew, vec![false; t], trunc)
            })
            .collect::<Result<Vec<_>, _>>();
        trajs.and_then(TaskDataset::new)
    };
    let (dataset, prompts) = (make(rng, 8), make(rng, 3));
    // The builders above cannot fail for these fixed, consistent shapes.
    let (Ok(dataset), Ok(prompts)) = (dataset, prompts) else {
        unreachable!("synthetic shapes are consistent")
    };
    TaskData { id: TaskId { env: "synthetic".into(), index }, dataset, prompts }
}

/// Losses of `steps` training steps on synthetic data.
pub fn run(seed: u64, steps: u64, device: Device) -> Result<Vec<StepStats>, tch::TchError> {
    let mut rng = Rng::seed_from_u64(seed);
    let tasks = [synthetic_task(0, &mut rng), synthetic_task(1, &mut rng)];
    let refs: Vec<&TaskData> = tasks.iter().collect();
    let norm = StateNorm::from_datasets(4, tasks.iter().map(|t| &t.dataset));
    let scfg =
        SamplerConfig { k: 10, batch_size_per_task: 8, ..SamplerConfig::reference(30.0, 30) };
    let mcfg = PromptDtConfig::reference(4, 2);
    let Ok(sampler) = BatchSampler::new(scfg, &refs, norm, mcfg.n_positions) else {
        unreachable!("the smoke settings are valid")
    };
    tch::manual_seed(seed as i64);
    let vs = VarStore::new(device);
    let model = PromptDt::new(&vs.root(), &mcfg);
    let ocfg = AdamWConfig { warmup_steps: 1, learning_rate: 1e-3, ..AdamWConfig::default() };
    let mut opt = Optimizer::new(&vs, &mcfg.parameter_names(), ocfg);
    (0..steps)
        .map(|i| {
            let batch = DeviceBatch::new(&sampler.sample(&mut rng), true, device);
            train_step(&model, &mut opt, &batch, LossOn::History, i)
        })
        .collect()
}
