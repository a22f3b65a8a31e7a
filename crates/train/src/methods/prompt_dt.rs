//! The Prompt-DT family: Prompt-DT, Prompt-MT-BC, MT-ORL and MT-BC-Finetune, one learner whose
//! [`Variant`] says which inputs the model sees (the prompt; the history's returns-to-go) and
//! whether it fine-tunes on each test task's demonstrations before evaluating it.

use super::learner::{
    adam_steps_of, adam_steps_value, write_tensors, CheckpointFiles, Evaluation, IterationAt,
    IterationMetrics, Learner, SavedSteps, Steppable, TaskEval,
};
use super::prompt_strategy::evaluate_strategy;
use crate::config::{compact, Adaptation, FinetuneData, Method, TestTime, TrainConfig};
use crate::error::RunError;
use crate::optim::{AdamWConfig, Optimizer, ParamState, SlotState};
use crate::setup::{Setup, Split};
use crate::step::{
    train_step, train_step_with, unreadable, DeviceBatch, LossOn, PendingStats, StepStats,
};
use crate::streams::{STREAM_DROPOUT, STREAM_INIT};
use pdt_base::seed::derive_seed;
use pdt_eval::{evaluate, summarise, EvalSettings, EvalTask, TaskResult};
use pdt_model::checkpoint;
use pdt_model::PromptDt;
use pdt_policy::plan_task;
use pdt_prompt::{BatchSampler, Rng};
use std::collections::BTreeMap;
use std::path::Path;
use tch::{nn::VarStore, Device, Tensor};

/// Which of the four methods: what the model is given and whether it adapts at test time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Variant {
    /// The task's prompt is prepended (Prompt-DT, Prompt-MT-BC).
    pub(crate) prompt: bool,
    /// The history's returns-to-go are zeroed in training (Prompt-MT-BC, MT-BC-Finetune); the
    /// evaluation's are then `eval.mt_bc_returns`.
    pub(crate) zero_returns: bool,
    /// Each test task's evaluation is preceded by fine-tuning a copy of the weights on its
    /// demonstrations (MT-BC-Finetune).
    pub(crate) finetune: bool,
}

impl Variant {
    pub(crate) fn of(method: Method) -> Self {
        Self {
            prompt: method.uses_prompt(),
            zero_returns: method.zeroes_history_returns(),
            // Asked of `Method`, not named: the transformer that adapts before it acts.
            finetune: method.is_transformer() && method.adapts_before_acting(),
        }
    }
}

/// Model and optimiser of a Prompt-DT-family run.
pub(crate) struct PromptDtLearner<'s> {
    setup: &'s Setup,
    variant: Variant,
    vs: VarStore,
    model: PromptDt,
    opt: Optimizer,
    /// The training tasks' batch sampler.
    sampler: BatchSampler<'s>,
}

impl<'s> PromptDtLearner<'s> {
    /// The model initialised from the run seed (libtorch's generator: hold `torch_rng_lock`).
    pub(crate) fn new(setup: &'s Setup, variant: Variant) -> Result<Self, RunError> {
        let sampler = setup.sampler(&setup.run_data.train_data)?;
        tch::manual_seed(derive_seed(setup.cfg.run.seed, STREAM_INIT, 0) as i64);
        let vs = VarStore::new(setup.device);
        let mut model = PromptDt::new(&vs.root(), &setup.run_data.model_cfg);
        // `train.last_block` (default `auto`): the state tokens only on CUDA, every token (the
        // reference's ops, bit for bit PyTorch's) on the CPU.
        model.set_last_block(crate::step::last_block(
            setup.cfg.train.last_block,
            setup.device,
            false,
        ));
        // `optim.flat` (default `auto`): the flat-buffer AdamW on CUDA, PyTorch's per-tensor one
        // on CPU. Both save the same per-parameter state, so a run resumes on either.
        let opt = Optimizer::new(
            &vs,
            &setup.run_data.model_cfg.parameter_names(),
            setup.cfg.optim.clone(),
        );
        Ok(Self { setup, variant, vs, model, opt, sampler })
    }
}

impl PromptDtLearner<'_> {
    /// The evaluation of every task of `split` as `test_time` says, with its prompt picks and
    /// adaptation log.
    fn evaluate_with(
        &mut self,
        split: Split,
        test_time: &TestTime,
        rng: &mut Rng,
    ) -> Result<Evaluation, RunError> {
        eval_tasks(self, split, test_time, rng)
    }
}

/// A Prompt-DT-family run in a pack (`pdt-pack`).
impl Steppable for PromptDtLearner<'_> {
    fn sample_batch(&self, rng: &mut Rng) -> DeviceBatch {
        DeviceBatch::new(&self.sampler.sample(rng), self.variant.prompt, self.setup.device)
    }

    fn export(&self) -> SlotState {
        SlotState::copy_of(&self.vs, &self.opt)
    }

    fn import(&mut self, state: SlotState) -> Result<(), RunError> {
        state
            .copy_into(&self.vs, &mut self.opt)
            .map_err(|e| RunError::Invalid(format!("a pack's run state: {e}")))
    }

    /// MT-BC-Finetune's test evaluation fine-tunes, drawing its dropout from where the last
    /// step left the generator: that step's dropout masks drawn again (re-seeded, then the same
    /// forward in training mode, its result dropped; the draws depend on the shapes alone, not
    /// the weights). Mirrors `crate::step::train_step`'s forward.
    fn replay_step_draws(&self, split: Split, last: Option<(u64, &DeviceBatch)>) -> bool {
        if !(self.variant.finetune && split == Split::Test) {
            return false;
        }
        if let Some((step, batch)) = last {
            tch::manual_seed(derive_seed(self.setup.cfg.run.seed, STREAM_DROPOUT, step) as i64);
            let (h, p) = (&batch.history, batch.prompt.as_ref());
            tch::no_grad(|| match (self.setup.cfg.train.loss_on, p) {
                (LossOn::PromptAndHistory, Some(p)) => {
                    let _ = self.model.forward_all_steps(h, Some(p), true);
                }
                _ => {
                    let _ = self.model.forward(h, p, true);
                }
            });
        }
        true
    }
}

/// What an iteration logs, from its steps' statistics read once, after its last step: reading a
/// step's loss waits for the device, which would otherwise idle while the host prepares each next
/// step. A divergence (a non-finite loss or gradient norm) is the error of its step, as reading
/// each at once would give, found after the rest of its iteration (which a stopped run never
/// saves).
pub fn read_iteration(
    at: IterationAt<'_>,
    cfg: &TrainConfig,
    steps: Vec<PendingStats>,
) -> Result<IterationMetrics, RunError> {
    let stats = PendingStats::read_all(steps).map_err(unreadable)?;
    for (i, st) in stats.iter().enumerate() {
        if !(st.loss.is_finite() && st.grad_norm.is_finite()) {
            let step = at.first_step + i as u64;
            return Err(diverged(at.dir, cfg, at.iteration, step, st));
        }
    }
    Ok(iteration_metrics(&stats))
}

/// What an iteration of `stats` logs: the mean loss, the mean gradient norm and the last rate.
fn iteration_metrics(stats: &[StepStats]) -> IterationMetrics {
    let n = stats.len() as f64;
    let mut columns = BTreeMap::new();
    columns
        .insert("train/grad_norm".to_string(), stats.iter().map(|s| s.grad_norm).sum::<f64>() / n);
    columns.insert("train/lr".to_string(), stats.last().map_or(0.0, |s| s.lr));
    IterationMetrics { loss: stats.iter().map(|s| s.loss).sum::<f64>() / n, columns }
}

impl Learner for PromptDtLearner<'_> {
    fn loss_metric(&self) -> &'static str {
        "train/action_loss"
    }

    fn train_iteration(
        &mut self,
        at: IterationAt<'_>,
        rng: &mut Rng,
    ) -> Result<IterationMetrics, RunError> {
        let setup = self.setup;
        let cfg = &setup.cfg;
        let sampler = &self.sampler;
        let stats = at.each_step(|step| {
            // Dropout draws come from libtorch's generator, re-seeded per gradient step so that a
            // resumed run continues the same stream and a packed run (`pdt-pack`), whose steps
            // interleave with other runs', draws the same masks as solo.
            tch::manual_seed(derive_seed(cfg.run.seed, STREAM_DROPOUT, step) as i64);
            let batch = DeviceBatch::new(&sampler.sample(rng), self.variant.prompt, setup.device);
            let (model, loss_on) = (&self.model, cfg.train.loss_on);
            let draw = pdt_model::dropout::Dropout::Draw;
            Ok(train_step_with(model, &mut self.opt, &batch, loss_on, step, draw))
        })?;
        read_iteration(at, cfg, stats)
    }

    fn evaluate(
        &mut self,
        split: Split,
        test_time: &TestTime,
        rng: &mut Rng,
    ) -> Result<Evaluation, RunError> {
        self.evaluate_with(split, test_time, rng)
    }

    /// Weights with the model's shape (`pdt_model::checkpoint`), then the Adam moments per
    /// parameter name; each written under a temporary name and renamed.
    fn save(&mut self, files: &CheckpointFiles) -> Result<serde_json::Value, RunError> {
        checkpoint::save(&self.vs, &files.weights, &self.model.cfg)?;
        let state = self.opt.state();
        let mut named: Vec<(String, Tensor)> = Vec::new();
        for (name, st) in &state {
            named.push((format!("exp_avg.{name}"), st.exp_avg.to_device(Device::Cpu)));
            named.push((format!("exp_avg_sq.{name}"), st.exp_avg_sq.to_device(Device::Cpu)));
        }
        write_tensors(&files.moments, &named)?;
        let steps: BTreeMap<String, u64> = state.iter().map(|(n, s)| (n.clone(), s.step)).collect();
        adam_steps_value(&steps, files)
    }

    fn load(&mut self, files: &CheckpointFiles, saved: SavedSteps<'_>) -> Result<(), RunError> {
        let corrupt =
            |path: &Path, message: String| RunError::Corrupt { path: path.into(), message };
        let adam_steps: BTreeMap<String, u64> = adam_steps_of(saved, files)?;
        if let Some((name, n)) = adam_steps.iter().find(|(_, &n)| n != saved.step) {
            return Err(corrupt(
                &files.state,
                format!("optimiser step {n} for `{name}` at step {}", saved.step),
            ));
        }
        checkpoint::load(&mut self.vs, &files.weights, &self.model.cfg)?;
        let opt_path = &files.moments;
        let tensors = checkpoint::read_float_tensors(opt_path)?;
        let mut state = BTreeMap::new();
        for (name, &step) in &adam_steps {
            let get = |k: String| {
                tensors
                    .get(&k)
                    .map(Tensor::shallow_clone)
                    .ok_or_else(|| corrupt(opt_path, format!("missing `{k}`")))
            };
            let st = ParamState {
                step,
                exp_avg: get(format!("exp_avg.{name}"))?,
                exp_avg_sq: get(format!("exp_avg_sq.{name}"))?,
            };
            state.insert(name.clone(), st);
        }
        self.opt.set_state(state).map_err(|e| corrupt(opt_path, e.to_string()))
    }

    fn load_weights(&mut self, path: &Path) -> Result<(), RunError> {
        checkpoint::load(&mut self.vs, path, &self.setup.run_data.model_cfg)?;
        Ok(())
    }
}

/// Evaluates the tasks of `split`, each with its own prompt, all episodes together, as
/// `test_time` says: the reference rule, a prompt strategy, or an adaptation to each test task
/// (`[eval.adapt]`'s, or fine-tuning a copy of the weights on its data).
fn eval_tasks(
    learner: &mut PromptDtLearner<'_>,
    split: Split,
    test_time: &TestTime,
    rng: &mut Rng,
) -> Result<Evaluation, RunError> {
    let setup = learner.setup;
    let data = setup.data(split);
    let sampler = setup.sampler(data)?;
    let make = |i: usize, rng: &mut Rng| -> Result<EvalTask, RunError> {
        let plan = plan_task(setup.cfg.run.method, &sampler, data, i, setup.cfg.eval.episodes, rng);
        let envs = (0..plan.seeds.len())
            .map(|_| setup.family.make(plan.index))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(EvalTask {
            name: plan.name,
            index: plan.index,
            envs,
            seeds: plan.seeds,
            prompt: plan.prompt,
        })
    };
    let settings = EvalSettings {
        k: setup.run_data.sampler_cfg.k,
        horizon: setup.preset.horizon,
        rtg_scale: setup.run_data.sampler_cfg.rtg_scale,
        target_return: setup.run_data.stats.target_return,
        returns: setup.eval_returns(),
        norm: setup.run_data.norm.clone(),
        max_batch: setup.cfg.eval.max_batch,
        device: setup.device,
        env_threads: setup.env_threads,
        inference: setup.cfg.eval.inference,
    };
    // An adaptation is of the test tasks; training tasks are evaluated with its strategy alone.
    let (select, adaptation) = match test_time {
        TestTime::Reference => (None, None),
        TestTime::Strategy(s) => (Some(s), None),
        TestTime::Adapt { from, adaptation } => (Some(from), Some(adaptation)),
    };
    let adaptation = adaptation.filter(|_| split == Split::Test);
    let select = select.filter(|s| !s.is_default());
    match adaptation {
        // `[eval.adapt]`: its own evaluation, starting from the strategy's prompt.
        Some(Adaptation::Prompt(adapt_cfg)) => {
            let strategy = select.cloned().unwrap_or_default();
            let a = super::adapt::evaluate_adapted(
                &learner.model,
                setup,
                data,
                &settings,
                &strategy,
                adapt_cfg,
                rng,
            )?;
            return Ok(Evaluation {
                tasks: plain(a.results),
                adapt_log: a.log,
                ..Default::default()
            });
        }
        Some(&Adaptation::Finetune { steps, batch, lr, data }) => {
            let tune = Finetune { steps, batch, lr, data };
            return finetune_each(learner, &sampler, &settings, &tune, rng, &make);
        }
        Some(Adaptation::Macaw { .. }) => {
            return Err(RunError::Invalid(format!(
                "MACAW's adaptation is MACAW's own; this run is {}",
                setup.cfg.run.method.name()
            )))
        }
        None => {}
    }
    // A prompt strategy other than the reference rule: its own evaluation.
    if let Some(strategy) = select {
        let s = evaluate_strategy(&learner.model, setup, data, &settings, strategy, rng)?;
        return Ok(Evaluation { tasks: plain(s.results), picks: s.picks, ..Default::default() });
    }
    let tasks = (0..data.tasks.len()).map(|i| make(i, rng)).collect::<Result<Vec<_>, _>>()?;
    let eps = evaluate(&learner.model, tasks, &settings)?;
    let positions: Vec<usize> = (0..data.tasks.len()).collect();
    Ok(Evaluation::of_tasks(plain(summarise_all(data, &positions, &eps))))
}

/// MT-BC-Finetune's fine-tuning before each test task: its steps, segments per step and
/// learning rate.
struct Finetune {
    steps: u64,
    batch: usize,
    lr: f64,
    data: FinetuneData,
}

/// Per task: adapts a copy of the weights on the task's demonstrations with a fresh optimiser,
/// evaluates, restores. (The reference shares one optimiser across the test tasks of an
/// evaluation, leaking Adam moments between them: pitfall 13, fixed here.)
fn finetune_each(
    learner: &mut PromptDtLearner<'_>,
    sampler: &BatchSampler<'_>,
    settings: &EvalSettings,
    tune: &Finetune,
    rng: &mut Rng,
    make: &dyn Fn(usize, &mut Rng) -> Result<EvalTask, RunError>,
) -> Result<Evaluation, RunError> {
    let setup = learner.setup;
    let data = setup.data(Split::Test);
    let snapshot: Vec<(String, Tensor)> =
        learner.vs.variables().into_iter().map(|(n, t)| (n, t.copy())).collect();
    let mut results = Vec::new();
    for i in 0..data.tasks.len() {
        let task = make(i, rng)?;
        let ocfg =
            AdamWConfig { learning_rate: tune.lr, warmup_steps: 1, ..setup.cfg.optim.clone() };
        let mut opt =
            Optimizer::new(&learner.vs, &setup.run_data.model_cfg.parameter_names(), ocfg);
        // The tuning's dropout comes from libtorch's generator (a packed run holds it for the
        // whole evaluation: `pdt-pack`); its episodes draw nothing from it.
        for s in 0..tune.steps {
            let seg = match tune.data {
                FinetuneData::Dataset => sampler.tail_segments(
                    i,
                    tune.batch,
                    setup.run_data.sampler_cfg.prompt_length,
                    rng,
                ),
                // The adaptations' data (P_i), for a fine-tuning matched to them.
                FinetuneData::Prompts => sampler.demo_segments(i, tune.batch, rng),
            };
            let history = crate::step::to_segments(&seg, setup.device);
            let batch = DeviceBatch { history, prompt: None };
            train_step(&learner.model, &mut opt, &batch, LossOn::History, s).map_err(unreadable)?;
        }
        let eps = evaluate(&learner.model, vec![task], settings)?;
        results.extend(summarise_all(data, &[i], &eps));
        tch::no_grad(|| {
            let vars = learner.vs.variables();
            for (n, saved) in &snapshot {
                if let Some(v) = vars.get(n) {
                    v.shallow_clone().copy_(saved);
                }
            }
        });
    }
    Ok(Evaluation::of_tasks(plain(results)))
}

/// The results of the tasks at `positions` (indices into `data.tasks`): the k-th task passed to
/// `evaluate` is `data.tasks[positions[k]]`, whose episodes carry `task_index == k`.
fn summarise_all(
    data: &pdt_data::MultiTaskDataset,
    positions: &[usize],
    eps: &[pdt_eval::EpisodeRecord],
) -> Vec<TaskResult> {
    positions
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            let id = &data.tasks[i].id;
            let mine: Vec<_> = eps.iter().filter(|e| e.task_index == k).collect();
            summarise(&id.to_string(), id.index, &mine)
        })
        .collect()
}

/// Results of a rule without a per-task adaptation record.
fn plain(results: Vec<TaskResult>) -> Vec<TaskEval> {
    results.into_iter().map(|result| TaskEval { result, adaptation: None }).collect()
}

/// The error of a non-finite loss or gradient: the step, the values and the likely causes.
fn diverged(dir: &Path, cfg: &TrainConfig, iteration: u64, step: u64, st: &StepStats) -> RunError {
    RunError::Invalid(format!(
        "{}: training diverged at iteration {iteration}, gradient step {step}: loss {}, gradient \
         norm {}. Likely causes: optim.learning_rate = {} too high, optim.eps = {} too small, or \
         extreme values in the data (data.dir {}). Resuming would repeat the same steps: fix the \
         configuration and train again.",
        dir.display(),
        compact(st.loss),
        compact(st.grad_norm),
        compact(cfg.optim.learning_rate),
        compact(cfg.optim.eps),
        cfg.data.dir.display()
    ))
}
