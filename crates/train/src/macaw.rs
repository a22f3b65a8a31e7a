//! A MACAW run (`run.method = "macaw"`): the same run directory, logs, checkpoints, resumption and
//! evaluation records as the Prompt-DT variants (`docs/run-directory.md`), around `pdt_macaw`'s
//! meta-training step and test-time adaptation. One iteration is `train.steps_per_iteration`
//! meta-steps; an evaluation adapts to each task's data, then rolls the adapted policy out.
//!
//! Randomness: model init, task and batch draws (one stream, position saved in checkpoints), and
//! each evaluation (adaptation rows and episode seeds) come from independent streams of the run seed.

use crate::run::{
    eval_rows, io_err, latest_checkpoint, read_json, torch_rng_lock, write_json, Latest, Log,
    Progress, RunError, Setup, Split, TrainOptions, TrainSummary, STREAM_BATCHES, STREAM_EVAL_TEST,
    STREAM_EVAL_TRAIN, STREAM_INIT,
};
use pdt_base::seed::derive_seed;
use pdt_eval::{summarise, EpisodeRecord, TaskResult};
use pdt_macaw::{Batch, Dims, MacawConfig, Optimisers, Params, StepStats, TaskBuffer};
use pdt_prompt::Rng;
use rand::{RngCore, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use tch::{Device, Kind, Tensor};

impl From<pdt_macaw::MacawError> for RunError {
    fn from(e: pdt_macaw::MacawError) -> Self {
        RunError::Invalid(e.to_string())
    }
}

/// Training state besides tensors (`checkpoints/state_<N>.json` of a MACAW run).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct MacawState {
    method: String,
    iteration: u64,
    step: u64,
    /// Position of the task/batch RNG (a u128, as a decimal string).
    batch_rng_word_pos: String,
    /// Steps taken by each outer Adam, per tensor, in `Optimisers::GROUPS` order.
    adam_steps: Vec<Vec<u64>>,
    metrics_lines: usize,
    eval_lines: usize,
    /// `false` for a resume point (see `run::TrainState::keep`); absent in older runs.
    #[serde(default = "keep_default")]
    keep: bool,
}

fn keep_default() -> bool {
    true
}

/// The model of a MACAW run: shapes, parameters, and the training tasks' and evaluation tasks'
/// buffers.
struct Model {
    dims: Dims,
    params: Params,
}

fn model(setup: &Setup) -> Model {
    let m = &setup.cfg.macaw;
    let dims = Dims::new(setup.stats.obs_dim, setup.stats.act_dim, m.width, m.depth);
    tch::manual_seed(derive_seed(setup.cfg.run.seed, STREAM_INIT, 0) as i64);
    let params = Params::init(&dims, m, Kind::Float, setup.device);
    Model { dims, params }
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

fn save(
    dir: &Path,
    mdl: &Model,
    opt: &Optimisers,
    state: &MacawState,
    keep: bool,
) -> Result<(), RunError> {
    let ck = dir.join("checkpoints");
    std::fs::create_dir_all(&ck).map_err(io_err(&ck))?;
    let (model, moments) =
        (format!("step_{}.safetensors", state.step), format!("state_{}.safetensors", state.step));
    let cpu = |t: &Tensor| t.detach().to_device(Device::Cpu).contiguous();
    let weights: Vec<(String, Tensor)> =
        mdl.params.named(&mdl.dims).into_iter().map(|(n, t)| (n, cpu(t))).collect();
    let mut adam: Vec<(String, Tensor)> = Vec::new();
    for (g, a) in Optimisers::GROUPS.iter().zip(&opt.adams) {
        for (i, (m, v)) in a.exp_avg.iter().zip(&a.exp_avg_sq).enumerate() {
            adam.push((format!("{g}.{i}.exp_avg"), cpu(m)));
            adam.push((format!("{g}.{i}.exp_avg_sq"), cpu(v)));
        }
    }
    for (name, tensors) in [(&model, &weights), (&moments, &adam)] {
        let tmp = ck.join(crate::run::temp_name(name));
        Tensor::write_safetensors(tensors, &tmp)
            .map_err(|e| RunError::Corrupt { path: tmp.clone(), message: e.to_string() })?;
        std::fs::rename(&tmp, ck.join(name)).map_err(io_err(&tmp))?;
    }
    write_json(&ck.join(format!("state_{}.json", state.step)), state)?;
    crate::run::commit_checkpoint(
        &ck,
        Latest { step: state.step, iteration: state.iteration, model, state: moments, keep },
    )
}

/// Reads a safetensors file of ours (size-checked) into a map.
fn read_tensors(path: &Path) -> Result<BTreeMap<String, Tensor>, RunError> {
    let meta = std::fs::metadata(path).map_err(io_err(path))?;
    if meta.len() > pdt_base::fs::MAX_TENSOR_FILE_BYTES {
        return Err(RunError::Corrupt {
            path: path.into(),
            message: format!("{} bytes, above the limit", meta.len()),
        });
    }
    Ok(Tensor::read_safetensors(path)
        .map_err(|e| RunError::Corrupt { path: path.into(), message: e.to_string() })?
        .into_iter()
        .collect())
}

/// Loads MACAW weights into `mdl`, every tensor by name and shape.
fn load_weights(path: &Path, mdl: &mut Model) -> Result<(), RunError> {
    let mut saved = read_tensors(path)?;
    let corrupt = |message: String| RunError::Corrupt { path: path.into(), message };
    if !saved.contains_key("rho_adv") {
        return Err(corrupt(
            "not MACAW weights (no `rho_adv`): the checkpoint is of another method, or the run's \
             config.toml was edited"
                .into(),
        ));
    }
    let dims = mdl.dims.clone();
    for (name, t) in mdl.params.named(&dims) {
        let s = saved.remove(&name).ok_or_else(|| corrupt(format!("missing `{name}`")))?;
        if s.size() != t.size() {
            return Err(corrupt(format!(
                "`{name}` has shape {:?}, the run's configuration {:?} (macaw.width / depth changed?)",
                s.size(),
                t.size()
            )));
        }
        if s.isfinite().all().int64_value(&[]) == 0 {
            return Err(corrupt(format!("`{name}` holds values that are not finite")));
        }
        tch::no_grad(|| t.shallow_clone().copy_(&s.to_kind(t.kind())));
    }
    if let Some(extra) = saved.keys().next() {
        return Err(corrupt(format!("unexpected tensor `{extra}`")));
    }
    Ok(())
}

fn load(
    dir: &Path,
    setup: &Setup,
    mdl: &mut Model,
    opt: &mut Optimisers,
) -> Result<Option<MacawState>, RunError> {
    let ck = dir.join("checkpoints");
    if !ck.join("latest.json").exists() {
        return Ok(None);
    }
    let latest = latest_checkpoint(dir)?;
    let state_path = ck.join(format!("state_{}.json", latest.step));
    let state: MacawState = read_json(&state_path)?;
    let per = setup.cfg.train.steps_per_iteration;
    if state.method != "macaw"
        || state.step != latest.step
        || state.iteration != latest.iteration
        || state.step != state.iteration.saturating_mul(per)
        || latest.state != format!("state_{}.safetensors", latest.step)
    {
        return Err(RunError::Corrupt {
            path: state_path,
            message: format!(
                "method {} iteration {} step {}; latest.json says iteration {} step {} (and \
                 train.steps_per_iteration = {per})",
                state.method, state.iteration, state.step, latest.iteration, latest.step
            ),
        });
    }
    crate::run::check_log_counts(
        &state_path,
        state.iteration,
        state.metrics_lines,
        state.eval_lines,
        setup,
    )?;
    load_weights(&ck.join(&latest.model), mdl)?;
    let path = ck.join(&latest.state);
    let moments = read_tensors(&path)?;
    if state.adam_steps.len() != opt.adams.len() {
        return Err(RunError::Corrupt {
            path: state_path,
            message: "adam_steps: one list per optimiser expected".into(),
        });
    }
    let device = setup.device;
    for ((g, a), steps) in
        Optimisers::GROUPS.iter().zip(opt.adams.iter_mut()).zip(&state.adam_steps)
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
    Ok(Some(state))
}

/// One task's evaluation and how far its adaptation went.
pub(crate) struct MacawResult {
    result: TaskResult,
    value_steps: usize,
    policy_steps: usize,
    /// Episodes ended by a non-finite action (`pdt_macaw::rollout::run_episodes`).
    failed_episodes: usize,
}

/// Evaluation log rows with the adaptation steps taken (fewer than `macaw.adapt_steps` where the
/// adaptation diverged: `pdt_macaw::adapt`) and the episodes a non-finite action ended.
fn rows(
    res: &[MacawResult],
    iteration: u64,
    step: u64,
    split: &str,
    target: f32,
) -> Vec<serde_json::Map<String, serde_json::Value>> {
    let plain: Vec<TaskResult> = res.iter().map(|r| r.result.clone()).collect();
    let mut rows = eval_rows(&plain, iteration, step, split, target);
    for (row, r) in rows.iter_mut().zip(res) {
        row.insert("adapt_value_steps".into(), r.value_steps.into());
        row.insert("adapt_policy_steps".into(), r.policy_steps.into());
        row.insert("failed_episodes".into(), r.failed_episodes.into());
    }
    rows
}

/// Adapts to each task of `split` on a batch of its own data and rolls the adapted policy out
/// (`eval.episodes` episodes per task).
fn eval_tasks(
    setup: &Setup,
    mdl: &Model,
    bufs: &[TaskBuffer],
    split: Split,
    iteration: u64,
) -> Result<Vec<MacawResult>, RunError> {
    let (data, stream) = match split {
        Split::Test => (&setup.test_data, STREAM_EVAL_TEST),
        Split::Train => (&setup.train_data, STREAM_EVAL_TRAIN),
    };
    let m = &setup.cfg.macaw;
    let mut rng = Rng::seed_from_u64(derive_seed(setup.cfg.run.seed, stream, iteration));
    let threads = match setup.cfg.eval.env_threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    };
    let mut out = Vec::with_capacity(data.tasks.len());
    for (t, buf) in data.tasks.iter().zip(bufs) {
        let batch = buf.sample(m.adapt_batch, false, &mut rng, setup.device)?;
        let adapted = pdt_macaw::adapt(&mdl.params, &mdl.dims, &batch, m);
        let policy = &adapted.policy;
        let seeds: Vec<u64> = (0..setup.cfg.eval.episodes).map(|_| rng.next_u64()).collect();
        let eps = pdt_macaw::rollout::run_episodes(
            setup.family.as_ref(),
            t.id.index,
            policy,
            &mdl.dims,
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
        out.push(MacawResult {
            result: summarise(&t.id.to_string(), t.id.index, &refs),
            value_steps: adapted.value_steps,
            policy_steps: adapted.policy_steps,
            failed_episodes: eps.iter().filter(|e| e.failed).count(),
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
    RunError::Invalid(format!(
        "{}: MACAW training diverged at iteration {iteration}, meta-step {step}: losses {:?}, \
         gradient norms {} (value) {} (policy). Likely causes: macaw.outer_value_lr = {} / \
         outer_policy_lr = {} / lrlr = {} too high, or extreme returns in the data. Resuming would \
         repeat the same steps: fix the configuration and train again.",
        dir.display(),
        st.losses,
        crate::config::compact(st.value_grad_norm),
        crate::config::compact(st.policy_grad_norm),
        crate::config::compact(m.outer_value_lr),
        crate::config::compact(m.outer_policy_lr),
        crate::config::compact(m.lrlr)
    ))
}

/// Trains (or resumes) a MACAW run in `dir`, set up by `run::train` (directory owned, `run.json`,
/// `config.toml` and `task_stats.json` written or checked).
pub(crate) fn train(
    setup: &Setup,
    dir: &Path,
    opts: TrainOptions<'_>,
) -> Result<TrainSummary, RunError> {
    let cfg = &setup.cfg;
    let m = &cfg.macaw;
    let train_bufs = buffers(&setup.train_data, m)?;
    let test_bufs = buffers(&setup.test_data, m)?;
    check_sizes(&train_bufs, &test_bufs, m)?;
    let mut mdl = model(setup);
    let mut opt = Optimisers::new(&mdl.params, m);
    let state = if opts.resume { load(dir, setup, &mut mdl, &mut opt)? } else { None };
    let (mut iteration, mut step) = state.as_ref().map_or((0, 0), |s| (s.iteration, s.step));
    if opts.resume && opts.resume_with.iterations.is_some() && iteration > cfg.train.iterations {
        return Err(RunError::Invalid(format!(
            "--iterations {}: the run in {} has already done {iteration} iterations; give at \
             least that many to extend it",
            cfg.train.iterations,
            dir.display()
        )));
    }
    let mut metrics = Log::open(dir, "metrics", state.as_ref().map_or(0, |s| s.metrics_lines))?;
    let mut evals = Log::open(dir, "eval", state.as_ref().map_or(0, |s| s.eval_lines))?;
    crate::run::record_resume_changes(dir, cfg, &opts.resume_with, opts.resume)?;
    let mut rng = Rng::seed_from_u64(derive_seed(cfg.run.seed, STREAM_BATCHES, 0));
    if let Some(s) = &state {
        let pos = s.batch_rng_word_pos.parse::<u128>().map_err(|e| RunError::Corrupt {
            path: dir.join("checkpoints"),
            message: format!("batch_rng_word_pos: {e}"),
        })?;
        rng.set_word_pos(pos);
    }
    let n_train = train_bufs.len();
    let (t, started) = (&cfg.train, std::time::Instant::now());
    let mut last_test = None;
    let mut done_here = 0;
    let progress = opts.progress;
    while iteration < t.iterations {
        if opts.stop_after_iterations.is_some_and(|n| done_here >= n) {
            return Ok(TrainSummary {
                dir: dir.into(),
                iterations_done: iteration,
                finished: false,
                last_test,
            });
        }
        let mut stats: Vec<StepStats> = Vec::with_capacity(t.steps_per_iteration as usize);
        for _ in 0..t.steps_per_iteration {
            let tasks = draw(&train_bufs, m, &mut rng, setup.device)?;
            let st = pdt_macaw::meta_step(&mut mdl.params, &mut opt, &mdl.dims, &tasks, n_train, m);
            if !st.is_finite() {
                return Err(diverged(dir, iteration + 1, step, &st, m));
            }
            stats.push(st);
            step += 1;
        }
        iteration += 1;
        done_here += 1;
        let n = stats.len().max(1) as f64;
        let mean = |f: &dyn Fn(&StepStats) -> f64| stats.iter().map(f).sum::<f64>() / n;
        let loss = mean(&|s| s.losses.policy_outer);
        let last_st = stats.last().cloned().unwrap_or_default();
        let row = serde_json::json!({
            "iteration": iteration, "step": step,
            "train/value_inner_loss": mean(&|s| s.losses.value_inner),
            "train/value_outer_loss": mean(&|s| s.losses.value_outer),
            "train/policy_inner_loss": mean(&|s| s.losses.policy_inner),
            "train/policy_outer_loss": loss,
            "train/value_grad_norm": mean(&|s| s.value_grad_norm),
            "train/policy_grad_norm": mean(&|s| s.policy_grad_norm),
            "train/inner_value_lr": last_st.value_lr, "train/inner_policy_lr": last_st.policy_lr,
            "train/adv_coef": last_st.adv_coef, "time/elapsed_s": metrics.elapsed_before + started.elapsed().as_secs_f64(),
        });
        metrics.append(&[row.as_object().cloned().unwrap_or_default()])?;
        let last = iteration == t.iterations;
        let mut test_return = None;
        if (iteration - 1) % t.test_eval_interval == 0 || last {
            let res = eval_tasks(setup, &mdl, &test_bufs, Split::Test, iteration)?;
            evals.append(&rows(&res, iteration, step, "test", setup.stats.target_return))?;
            let res: Vec<TaskResult> = res.into_iter().map(|r| r.result).collect();
            test_return =
                Some(res.iter().map(|r| r.return_mean).sum::<f64>() / res.len().max(1) as f64);
            last_test = Some(res);
        }
        if t.train_eval_interval > 0 && ((iteration - 1) % t.train_eval_interval == 0 || last) {
            let res = eval_tasks(setup, &mdl, &train_bufs, Split::Train, iteration)?;
            evals.append(&rows(&res, iteration, step, "train", setup.stats.target_return))?;
        }
        let keep = iteration % t.save_interval == 0 || last;
        if keep || (t.resume_interval > 0 && iteration % t.resume_interval == 0) {
            let state = MacawState {
                method: "macaw".into(),
                iteration,
                step,
                batch_rng_word_pos: rng.get_word_pos().to_string(),
                adam_steps: opt.adams.iter().map(|a| a.steps.clone()).collect(),
                metrics_lines: metrics.lines,
                eval_lines: evals.lines,
                keep,
            };
            save(dir, &mdl, &opt, &state, keep)?;
        }
        progress(&Progress { iteration, iterations: t.iterations, loss, test_return });
    }
    Ok(TrainSummary { dir: dir.into(), iterations_done: iteration, finished: true, last_test })
}

/// `promptdt eval` of a MACAW run: its latest weights, adapted to each task of `split` afresh.
pub(crate) fn evaluate(
    setup: &Setup,
    dir: &Path,
    split: Split,
) -> Result<(Latest, Vec<TaskResult>), RunError> {
    let _rng = torch_rng_lock();
    let m = &setup.cfg.macaw;
    let data = match split {
        Split::Test => &setup.test_data,
        Split::Train => &setup.train_data,
    };
    let bufs = buffers(data, m)?;
    let mut rng = Rng::seed_from_u64(0);
    for b in &bufs {
        b.sample(m.adapt_batch, false, &mut rng, Device::Cpu)?;
    }
    let mut mdl = model(setup);
    let latest = latest_checkpoint(dir)?;
    load_weights(&dir.join("checkpoints").join(&latest.model), &mut mdl)?;
    let tasks = eval_tasks(setup, &mdl, &bufs, split, u64::MAX - latest.iteration)?;
    Ok((latest, tasks.into_iter().map(|r| r.result).collect()))
}
