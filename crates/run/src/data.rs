//! A run's data as its configuration names them: the training and test tasks' datasets and prompt
//! sets, the state normalisation computed over them, the sampler's settings, and the statistics a
//! run records (`task_stats.json`), with every check that a policy can act on them (dims, return
//! tokens, state statistics, episode lengths against the model's timestep table).
//!
//! The trainer builds its setup from the same loader, so that a served policy's prompts are the
//! evaluation's.

use crate::LoadError;
use pdt_base::num::compact;
use pdt_data::multitask::{load_multitask, DatasetSpec};
use pdt_data::{MultiTaskDataset, TaskData};
use pdt_envs::{EnvFamily, EnvPreset};
use pdt_eval::ToModelConfig;
use pdt_model::PromptDtConfig;
use pdt_prompt::{BatchSampler, NormalizationScope, SamplerConfig, StateNorm};
use pdt_rundir::config::{within, TrainConfig, MAX_RETURN_TOKEN, MAX_STATE_STAT};
use pdt_rundir::RunStats;

/// Everything built from a configuration's data section and its data.
pub struct RunData {
    pub train_data: MultiTaskDataset,
    pub test_data: MultiTaskDataset,
    pub norm: StateNorm,
    pub sampler_cfg: SamplerConfig,
    pub model_cfg: PromptDtConfig,
    /// What a run records of them (`task_stats.json`).
    pub stats: RunStats,
}

impl RunData {
    /// Loads the data of `cfg` (a validated configuration) for `family` and checks them.
    pub fn load(cfg: &TrainConfig, family: &dyn EnvFamily) -> Result<Self, LoadError> {
        let preset = family.preset();
        let (train_tasks, test_tasks) = family.split(&cfg.env.split)?;
        let env_name = family.name().to_string();
        let spec = |tasks: &[usize], d: &str, p: &str| DatasetSpec {
            dir: cfg.data.dir.clone(),
            env: env_name.clone(),
            tasks: tasks.to_vec(),
            dataset_mode: d.to_string(),
            prompt_mode: p.to_string(),
            format: cfg.data.format,
        };
        let train_data =
            load_multitask(&spec(&train_tasks, &cfg.data.dataset_mode, &cfg.data.prompt_mode))?;
        let test_data = load_multitask(&spec(
            &test_tasks,
            &cfg.data.test_dataset_mode,
            &cfg.data.test_prompt_mode,
        ))?;
        let (ds, da) = (train_data.obs_dim, train_data.act_dim);
        if (ds, da) != (preset.obs_dim, preset.act_dim)
            || (test_data.obs_dim, test_data.act_dim) != (ds, da)
        {
            return Err(LoadError::Invalid(format!(
                "data in {} has obs/act dims {ds}/{da} (test {}/{}), but {} has {}/{}",
                cfg.data.dir.display(),
                test_data.obs_dim,
                test_data.act_dim,
                env_name,
                preset.obs_dim,
                preset.act_dim
            )));
        }
        let train_ds = train_data.tasks.iter().map(|t| &t.dataset);
        // Reference quirk (pitfall 4): the statistics include the test tasks' datasets.
        let norm = match cfg.data.normalization {
            NormalizationScope::TrainAndTest => StateNorm::from_datasets(
                ds,
                train_ds.chain(test_data.tasks.iter().map(|t| &t.dataset)),
            ),
            NormalizationScope::TrainOnly => StateNorm::from_datasets(ds, train_ds),
            NormalizationScope::None => StateNorm::identity(ds),
        };
        let s = &cfg.sampler;
        let sampler_cfg = SamplerConfig {
            k: s.k,
            prompt_episodes: s.prompt_episodes,
            prompt_length: s.prompt_length.unwrap_or(preset.prompt_length),
            prompt_position: s.prompt_position,
            batch_size_per_task: s.batch_size_per_task,
            rtg_scale: s.rtg_scale.unwrap_or(preset.rtg_scale),
            max_ep_len: preset.horizon,
            ranking: s.ranking,
            zero_history_returns: cfg.run.method.zeroes_history_returns(),
        };
        if cfg.run.method.is_transformer() {
            check_return_tokens(cfg, &preset, &env_name, &train_data, &test_data)?;
        }
        if cfg.data.normalization != NormalizationScope::None {
            check_state_stats(cfg, &env_name, &norm, &train_data, &test_data)?;
        }
        // Timesteps index the embedding table: an episode longer than it would index past it.
        let longest = train_data
            .tasks
            .iter()
            .chain(&test_data.tasks)
            .flat_map(|t| t.dataset.trajectories.iter().chain(&t.prompts.trajectories))
            .map(|t| t.len())
            .max()
            .unwrap_or(0)
            .max(preset.horizon);
        if cfg.model.max_ep_len < longest {
            return Err(LoadError::Invalid(format!(
                "model.max_ep_len = {} is below the longest episode ({longest} steps: {}'s \
                 horizon or its data); timesteps would index past the embedding table",
                cfg.model.max_ep_len, env_name
            )));
        }
        let model_cfg = cfg.model.to_model_config(ds, da);
        model_cfg.validate().map_err(LoadError::Invalid)?;
        sampler_cfg.validate(model_cfg.n_positions)?;
        let stats = RunStats {
            obs_dim: ds,
            act_dim: da,
            state_mean: norm.mean.clone(),
            state_std: norm.std.clone(),
            rtg_scale: sampler_cfg.rtg_scale,
            target_return: cfg.eval.target_return.unwrap_or(preset.target_return),
            horizon: preset.horizon,
            train_tasks,
            test_tasks,
            train_data_fingerprint: train_data.fingerprint(),
            test_data_fingerprint: test_data.fingerprint(),
        };
        Ok(Self { train_data, test_data, norm, sampler_cfg, model_cfg, stats })
    }

    /// The sampler over `data`'s tasks (one of this run's two sets).
    pub fn sampler<'a>(&self, data: &'a MultiTaskDataset) -> Result<BatchSampler<'a>, LoadError> {
        let tasks: Vec<&TaskData> = data.tasks.iter().collect();
        Ok(BatchSampler::new(
            self.sampler_cfg.clone(),
            &tasks,
            self.norm.clone(),
            self.model_cfg.n_positions,
        )?)
    }
}

/// How a setting with a preset default is named in messages: `sampler.rtg_scale = 1e-30` when set,
/// `the rtg scale 10 (point_robot's preset; sampler.rtg_scale)` when not.
fn setting(name: &str, what: &str, set: Option<f32>, preset: f32, env: &str) -> String {
    match set {
        Some(x) => format!("{name} = {}", compact(x)),
        None => format!("the {what} {} ({env}'s preset; {name})", compact(preset)),
    }
}

/// A value computed in f64 from f32 settings, printed as the f32 it is close to (`1e29`, not
/// `1.0000000150474662e29`) when it is one.
fn shown(x: f64) -> String {
    let y = x as f32;
    if y.is_finite() {
        compact(y)
    } else {
        compact(x)
    }
}

/// The file of task `t`'s data of kind `mode` (`expert`, `prompt-expert`), for messages; the task
/// and mode when it cannot be found again.
fn task_file(cfg: &TrainConfig, env: &str, t: &TaskData, mode: &str) -> String {
    pdt_data::multitask::resolve_task_file(&cfg.data.dir, env, t.id.index, mode, cfg.data.format)
        .map_or_else(|_| format!("task {}'s {mode} data", t.id), |p| p.display().to_string())
}

/// Refuses return-to-go tokens the model cannot represent: the target return's (the first token of
/// every evaluation episode) and the data's (training and prompt tokens), each over the rtg scale,
/// must stay within [`MAX_RETURN_TOKEN`] in magnitude.
fn check_return_tokens(
    cfg: &TrainConfig,
    preset: &EnvPreset,
    env: &str,
    train: &MultiTaskDataset,
    test: &MultiTaskDataset,
) -> Result<(), LoadError> {
    let scale = cfg.sampler.rtg_scale.unwrap_or(preset.rtg_scale);
    let scale_name = setting("sampler.rtg_scale", "rtg scale", cfg.sampler.rtg_scale, scale, env);
    let target = cfg.eval.target_return.unwrap_or(preset.target_return);
    let token = f64::from(target) / f64::from(scale);
    if !within(token, MAX_RETURN_TOKEN) {
        let target_name =
            setting("eval.target_return", "target return", cfg.eval.target_return, target, env);
        return Err(LoadError::Invalid(format!(
            "{target_name} over {scale_name} gives the return token {}, beyond {} in magnitude: \
             the model cannot represent it (its return embedding overflows f32 and the actions \
             come out NaN). Lower eval.target_return or raise sampler.rtg_scale",
            shown(token),
            compact(MAX_RETURN_TOKEN)
        )));
    }
    // The largest return-to-go of the data (from any step, D_i and P_i alike), and where it is.
    let d = &cfg.data;
    let mut worst: Option<(f64, &TaskData, String, usize, usize)> = None;
    for (set, modes) in [
        (train, (&d.dataset_mode, &d.prompt_mode)),
        (test, (&d.test_dataset_mode, &d.test_prompt_mode)),
    ] {
        for t in &set.tasks {
            for (trajs, mode) in
                [(&t.dataset, modes.0.clone()), (&t.prompts, format!("prompt-{}", modes.1))]
            {
                for (k, tr) in trajs.trajectories.iter().enumerate() {
                    let mut rtg = 0f64;
                    for (step, r) in tr.rewards.iter().enumerate().rev() {
                        rtg += f64::from(*r);
                        if worst.as_ref().is_none_or(|w| rtg.abs() > w.0.abs()) {
                            worst = Some((rtg, t, mode.clone(), k, step));
                        }
                    }
                }
            }
        }
    }
    if let Some((rtg, t, mode, k, step)) = worst {
        let token = rtg / f64::from(scale);
        if !within(token, MAX_RETURN_TOKEN) {
            return Err(LoadError::Invalid(format!(
                "the return-to-go {} of {} (trajectory {k}, from step {step}) over {scale_name} \
                 gives the return token {}, beyond {} in magnitude: the model cannot represent \
                 it. Raise sampler.rtg_scale",
                shown(rtg),
                task_file(cfg, env, t, &mode),
                shown(token),
                compact(MAX_RETURN_TOKEN)
            )));
        }
    }
    Ok(())
}

/// Refuses state statistics that are not finite or absurd (beyond [`MAX_STATE_STAT`]), naming the
/// dimension and the file holding the observation that made them so. A non-finite statistic
/// could not even be recorded (`task_stats.json` would hold `null`).
fn check_state_stats(
    cfg: &TrainConfig,
    env: &str,
    norm: &StateNorm,
    train: &MultiTaskDataset,
    test: &MultiTaskDataset,
) -> Result<(), LoadError> {
    let bad = |x: f32| !within(f64::from(x), MAX_STATE_STAT);
    let Some(j) = (0..norm.mean.len()).find(|&j| bad(norm.mean[j]) || bad(norm.std[j])) else {
        return Ok(());
    };
    // The datasets the statistics were computed over (`StateNorm::from_datasets` in `load`).
    let mut sets: Vec<(&TaskData, &str)> =
        train.tasks.iter().map(|t| (t, cfg.data.dataset_mode.as_str())).collect();
    if cfg.data.normalization == NormalizationScope::TrainAndTest {
        sets.extend(test.tasks.iter().map(|t| (t, cfg.data.test_dataset_mode.as_str())));
    }
    let od = norm.mean.len();
    let mut worst: Option<(f32, &TaskData, &str, usize, usize)> = None;
    for &(t, mode) in &sets {
        for (k, tr) in t.dataset.trajectories.iter().enumerate() {
            for (step, row) in tr.observations.chunks_exact(od).enumerate() {
                if worst.as_ref().is_none_or(|w| row[j].abs() > w.0.abs()) {
                    worst = Some((row[j], t, mode, k, step));
                }
            }
        }
    }
    let at = match worst {
        Some((x, t, mode, k, step)) => {
            let file = task_file(cfg, env, t, mode);
            format!(
                "; the largest magnitude there is observations[{j}] = {} in {file} (trajectory \
                 {k}, step {step})",
                compact(x)
            )
        }
        None => String::new(),
    };
    Err(LoadError::Invalid(format!(
        "the state statistics (data.normalization = {}) have state_mean[{j}] = {} and \
         state_std[{j}] = {}: each must be finite and within {} in magnitude{at}. Normalising by \
         them would map every ordinary state to about 0 (or NaN); fix the data",
        serde_json::to_string(&cfg.data.normalization).unwrap_or_default(),
        compact(norm.mean[j]),
        compact(norm.std[j]),
        compact(MAX_STATE_STAT)
    )))
}
