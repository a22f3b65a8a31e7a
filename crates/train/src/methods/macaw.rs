//! MACAW (`run.method = "macaw"`): `pdt_macaw`'s meta-training step and test-time adaptation as
//! a [`Learner`], so that a MACAW run has the same run directory, logs, checkpoints, resumption
//! and evaluation records as the Prompt-DT variants (`docs/run-directory.md`). One iteration is
//! `train.steps_per_iteration` meta-steps; an evaluation adapts to each task's data, then rolls
//! the adapted policy out.
//!
//! Randomness: model init, task and batch draws (the run's batch stream), and each evaluation
//! (adaptation rows and episode seeds) come from independent streams of the run seed.

use super::learner::{
    adam_steps_of, adam_steps_value, write_tensors, CheckpointFiles, Evaluation, IterationAt,
    IterationMetrics, Learner, SavedSteps, TaskEval,
};
use crate::error::RunError;
use crate::setup::{Setup, Split};
use pdt_base::num::compact;
use pdt_base::seed::derive_seed;
use pdt_eval::{summarise, EpisodeRecord};
use pdt_macaw::{Batch, Dims, Optimisers, Params, StepStats, TaskBuffer};
use pdt_model::checkpoint;
use pdt_prompt::Rng;
use pdt_run::streams::STREAM_INIT;
use pdt_rundir::config::macaw::MacawConfig;
use pdt_rundir::config::{Adaptation, TestTime};
use pdt_rundir::AdaptationStats;
use rand::{RngCore, SeedableRng};
use std::collections::BTreeMap;
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// The model of a MACAW run with its outer optimisers, and the training and test tasks' buffers.
pub(crate) struct MacawLearner<'s> {
    setup: &'s Setup,
    /// The run's `[macaw]` section (an evaluation's adaptation budget is its [`TestTime`]'s).
    m: MacawConfig,
    dims: Dims,
    params: Params,
    opt: Optimisers,
    train_bufs: Vec<TaskBuffer>,
    test_bufs: Vec<TaskBuffer>,
}

impl<'s> MacawLearner<'s> {
    /// The model initialised from the run seed (libtorch's generator: hold `torch_rng_lock`).
    pub(crate) fn new(setup: &'s Setup) -> Result<Self, RunError> {
        let m = setup.cfg.macaw.clone();
        let train_bufs = buffers(&setup.run_data.train_data, &m)?;
        let test_bufs = buffers(&setup.run_data.test_data, &m)?;
        let dims =
            Dims::new(setup.run_data.stats.obs_dim, setup.run_data.stats.act_dim, m.width, m.depth);
        tch::manual_seed(derive_seed(setup.cfg.run.seed, STREAM_INIT, 0) as i64);
        let params = Params::init(&dims, &m, Kind::Float, setup.device);
        let opt = Optimisers::new(&params, &m);
        Ok(Self { setup, m, dims, params, opt, train_bufs, test_bufs })
    }
}

impl Learner for MacawLearner<'_> {
    fn loss_metric(&self) -> &'static str {
        "train/policy_outer_loss"
    }

    fn state_tag(&self) -> Option<&'static str> {
        Some("macaw")
    }

    fn check_can_train(&self) -> Result<(), RunError> {
        check_sizes(&self.train_bufs, &self.test_bufs, &self.m)
    }

    fn train_iteration(
        &mut self,
        at: IterationAt<'_>,
        rng: &mut Rng,
    ) -> Result<IterationMetrics, RunError> {
        let (m, device, n_train) = (&self.m, self.setup.device, self.train_bufs.len());
        let stats = at.each_step(|step| {
            let tasks = draw(&self.train_bufs, m, rng, device)?;
            let st = pdt_macaw::meta_step(
                &mut self.params,
                &mut self.opt,
                &self.dims,
                &tasks,
                n_train,
                m,
            );
            if st.is_finite() {
                Ok(st)
            } else {
                Err(diverged(at.dir, at.iteration, step, &st, m))
            }
        })?;
        let n = stats.len().max(1) as f64;
        let mean = |f: &dyn Fn(&StepStats) -> f64| stats.iter().map(f).sum::<f64>() / n;
        let last = stats.last().cloned().unwrap_or_default();
        let mut columns = BTreeMap::new();
        for (name, value) in [
            ("train/value_inner_loss", mean(&|s| s.losses.value_inner)),
            ("train/value_outer_loss", mean(&|s| s.losses.value_outer)),
            ("train/policy_inner_loss", mean(&|s| s.losses.policy_inner)),
            ("train/value_grad_norm", mean(&|s| s.value_grad_norm)),
            ("train/policy_grad_norm", mean(&|s| s.policy_grad_norm)),
            ("train/inner_value_lr", last.value_lr),
            ("train/inner_policy_lr", last.policy_lr),
            ("train/adv_coef", last.adv_coef),
        ] {
            columns.insert(name.to_string(), value);
        }
        Ok(IterationMetrics { loss: mean(&|s| s.losses.policy_outer), columns })
    }

    fn evaluate(
        &mut self,
        split: Split,
        test_time: &TestTime,
        rng: &mut Rng,
    ) -> Result<Evaluation, RunError> {
        let bufs = match split {
            Split::Test => &self.test_bufs,
            Split::Train => &self.train_bufs,
        };
        // MACAW's policy is its adaptation, on training tasks too: the budget is the test time's.
        let mut m = self.m.clone();
        match test_time.adaptation() {
            Some(&Adaptation::Macaw { steps, batch }) => {
                (m.adapt_steps, m.adapt_batch) = (steps, batch)
            }
            Some(Adaptation::Prompt(_) | Adaptation::Finetune { .. }) | None => {
                return Err(RunError::invalid(
                    "test time",
                    "MACAW evaluates through its own adaptation ([macaw]'s adapt_steps and \
                     adapt_batch), not a prompt strategy or another adaptation",
                ))
            }
        }
        eval_tasks(self, &m, bufs, split, rng).map(Evaluation::of_tasks)
    }

    /// Weights and the outer Adams' moments, each as one safetensors file written under a
    /// temporary name and renamed.
    fn save(&mut self, files: &CheckpointFiles) -> Result<serde_json::Value, RunError> {
        let cpu = |t: &Tensor| t.detach().to_device(Device::Cpu).contiguous();
        let weights: Vec<(String, Tensor)> =
            self.params.named(&self.dims).into_iter().map(|(n, t)| (n, cpu(t))).collect();
        let mut adam: Vec<(String, Tensor)> = Vec::new();
        for (g, a) in Optimisers::GROUPS.iter().zip(&self.opt.adams) {
            for (i, (m, v)) in a.exp_avg.iter().zip(&a.exp_avg_sq).enumerate() {
                adam.push((format!("{g}.{i}.exp_avg"), cpu(m)));
                adam.push((format!("{g}.{i}.exp_avg_sq"), cpu(v)));
            }
        }
        write_tensors(&files.weights, &weights)?;
        write_tensors(&files.moments, &adam)?;
        // Steps taken by each outer Adam, per tensor, in `Optimisers::GROUPS` order.
        let steps: Vec<Vec<u64>> = self.opt.adams.iter().map(|a| a.steps.clone()).collect();
        adam_steps_value(&steps, files)
    }

    fn load(&mut self, files: &CheckpointFiles, saved: SavedSteps<'_>) -> Result<(), RunError> {
        let state_path = &files.state;
        let adam_steps: Vec<Vec<u64>> = adam_steps_of(saved, files)?;
        load_weights(&files.weights, &mut self.params, &self.dims)?;
        let path = &files.moments;
        let moments = checkpoint::read_float_tensors(path)?;
        if adam_steps.len() != self.opt.adams.len() {
            return Err(RunError::Corrupt {
                path: state_path.clone(),
                message: "adam_steps: one list per optimiser expected".into(),
            });
        }
        let device = self.setup.device;
        for ((g, a), steps) in
            Optimisers::GROUPS.iter().zip(self.opt.adams.iter_mut()).zip(&adam_steps)
        {
            if steps.len() != a.steps.len() {
                return Err(RunError::Corrupt {
                    path: state_path.clone(),
                    message: format!(
                        "adam_steps of `{g}`: {} entries for {} tensors",
                        steps.len(),
                        a.steps.len()
                    ),
                });
            }
            a.steps.clone_from(steps);
            for i in 0..a.steps.len() {
                for (key, slot) in
                    [("exp_avg", &mut a.exp_avg[i]), ("exp_avg_sq", &mut a.exp_avg_sq[i])]
                {
                    let name = format!("{g}.{i}.{key}");
                    let t = moments.get(&name).ok_or_else(|| RunError::Corrupt {
                        path: path.clone(),
                        message: format!("missing `{name}`"),
                    })?;
                    if t.size() != slot.size() {
                        return Err(RunError::Corrupt {
                            path: path.clone(),
                            message: format!("`{name}`: shape {:?}", t.size()),
                        });
                    }
                    *slot = t.to_kind(slot.kind()).to_device(device);
                }
            }
        }
        Ok(())
    }

    fn load_weights(&mut self, path: &Path) -> Result<(), RunError> {
        load_weights(path, &mut self.params, &self.dims)
    }
}

fn buffers(
    data: &pdt_data::MultiTaskDataset,
    m: &MacawConfig,
) -> Result<Vec<TaskBuffer>, RunError> {
    let spec = pdt_macaw::buffer_spec(m);
    Ok(data
        .tasks
        .iter()
        .map(|t| TaskBuffer::from_dataset(&t.id.to_string(), &t.dataset, &spec))
        .collect::<Result<Vec<_>, _>>()?)
}

/// Checks up front that every buffer can give the batches the configuration asks for.
fn check_sizes(train: &[TaskBuffer], test: &[TaskBuffer], m: &MacawConfig) -> Result<(), RunError> {
    let mut rng = Rng::seed_from_u64(0);
    for b in train {
        b.sample(m.inner_batch, m.contiguous_inner, &mut rng, Device::Cpu)?;
        b.sample(m.outer_batch, false, &mut rng, Device::Cpu)?;
    }
    for b in test {
        b.sample(m.adapt_batch, false, &mut rng, Device::Cpu)?;
    }
    Ok(())
}

/// Loads MACAW weights into `params`, every tensor by name and shape.
fn load_weights(path: &Path, params: &mut Params, dims: &Dims) -> Result<(), RunError> {
    let mut saved = checkpoint::read_float_tensors_of(path, |names| {
        if names.iter().any(|n| n == "rho_adv") {
            return Ok(());
        }
        Err("not MACAW weights (no `rho_adv`): the checkpoint is of another method, or the run's \
             config.toml was edited"
            .into())
    })?;
    let corrupt = |message: String| RunError::Corrupt { path: path.into(), message };
    for (name, t) in params.named(dims) {
        let s = saved.remove(&name).ok_or_else(|| corrupt(format!("missing `{name}`")))?;
        if s.size() != t.size() {
            return Err(corrupt(format!(
                "`{name}` has shape {:?}, the run's configuration {:?} (macaw.width / depth changed?)",
                s.size(),
                t.size()
            )));
        }
        tch::no_grad(|| t.shallow_clone().copy_(&s.to_kind(t.kind())));
    }
    if let Some(extra) = saved.keys().next() {
        return Err(corrupt(format!("unexpected tensor `{extra}`")));
    }
    Ok(())
}

/// Adapts to each task of `split` on a batch of its own data and rolls the adapted policy out
/// (`eval.episodes` episodes per task).
fn eval_tasks(
    l: &MacawLearner<'_>,
    m: &MacawConfig,
    bufs: &[TaskBuffer],
    split: Split,
    rng: &mut Rng,
) -> Result<Vec<TaskEval>, RunError> {
    let setup = l.setup;
    let data = setup.data(split);
    let threads = setup.env_threads;
    let mut out = Vec::with_capacity(data.tasks.len());
    for (t, buf) in data.tasks.iter().zip(bufs) {
        let batch = buf.sample(m.adapt_batch, false, rng, setup.device)?;
        let adapted = pdt_macaw::adapt(&l.params, &l.dims, &batch, m);
        let policy = &adapted.policy;
        let seeds: Vec<u64> = (0..setup.cfg.eval.episodes).map(|_| rng.next_u64()).collect();
        let eps = pdt_macaw::rollout::run_episodes(
            setup.family.as_ref(),
            t.id.index,
            policy,
            &l.dims,
            m,
            &seeds,
            threads,
            setup.device,
        )?;
        let recs: Vec<EpisodeRecord> = eps
            .iter()
            .map(|e| EpisodeRecord {
                task_index: t.id.index,
                seed: e.seed,
                episode_return: e.episode_return,
                length: e.length,
                success: e.success,
                actions: Vec::new(),
            })
            .collect();
        let refs: Vec<&EpisodeRecord> = recs.iter().collect();
        // The adaptation steps taken (fewer than `macaw.adapt_steps` where the adaptation
        // diverged: `pdt_macaw::adapt`) and the episodes a non-finite action ended.
        let adaptation = AdaptationStats {
            adapt_value_steps: adapted.value_steps,
            adapt_policy_steps: adapted.policy_steps,
            failed_episodes: eps.iter().filter(|e| e.failed).count(),
        };
        out.push(TaskEval {
            result: summarise(&t.id.to_string(), t.id.index, &refs),
            adaptation: Some(adaptation),
        });
    }
    Ok(out)
}

/// One meta-step's batches: `task_batch` training tasks drawn without replacement (all when there
/// are fewer), in task order, each with an inner and an outer batch.
fn draw(
    bufs: &[TaskBuffer],
    m: &MacawConfig,
    rng: &mut Rng,
    device: Device,
) -> Result<Vec<(Batch, Batch)>, RunError> {
    let mut tasks: Vec<usize> = if bufs.len() <= m.task_batch {
        (0..bufs.len()).collect()
    } else {
        rand::seq::index::sample(rng, bufs.len(), m.task_batch).into_vec()
    };
    tasks.sort_unstable();
    tasks
        .into_iter()
        .map(|i| {
            let d_in = bufs[i].sample(m.inner_batch, m.contiguous_inner, rng, device)?;
            let d_out = bufs[i].sample(m.outer_batch, false, rng, device)?;
            Ok((d_in, d_out))
        })
        .collect()
}

fn diverged(dir: &Path, iteration: u64, step: u64, st: &StepStats, m: &MacawConfig) -> RunError {
    RunError::Diverged {
        dir: dir.into(),
        message: format!(
            "MACAW training diverged at iteration {iteration}, meta-step {step}: losses {:?}, \
         gradient norms {} (value) {} (policy). Likely causes: macaw.outer_value_lr = {} / \
         outer_policy_lr = {} / lrlr = {} too high, or extreme returns in the data. Resuming would \
         repeat the same steps: fix the configuration and train again.",
            st.losses,
            compact(st.value_grad_norm),
            compact(st.policy_grad_norm),
            compact(m.outer_value_lr),
            compact(m.outer_policy_lr),
            compact(m.lrlr)
        ),
    }
}
