//! The Prompt-DT family: Prompt-DT, Prompt-MT-BC, MT-ORL and MT-BC-Finetune, one learner whose
//! [`Variant`] says which inputs the model sees (the prompt; the history's returns-to-go) and
//! whether it fine-tunes on each test task's demonstrations before evaluating it.

use super::learner::{
    adam_steps_of, adam_steps_value, write_tensors, CheckpointFiles, Evaluation, IterationAt,
    IterationMetrics, Learner, SavedSteps, Steppable, TaskEval,
};
use crate::error::RunError;
use crate::optim::{Optimizer, ParamState, SlotState};
use crate::setup::{Setup, Split};
use crate::step::{train_step_with, unreadable, DeviceBatch, PendingStats, StepStats};
use pdt_base::num::compact;
use pdt_base::seed::derive_seed;
use pdt_eval::testtime::{self, SplitEval};
use pdt_eval::EvalSettings;
use pdt_model::checkpoint;
use pdt_model::prompt_dt::Sequence;
use pdt_model::PromptDt;
use pdt_prompt::{BatchSampler, Rng};
use pdt_run::streams::{STREAM_DROPOUT, STREAM_INIT};
use pdt_rundir::config::{Adaptation, LossOn, Method, TestTime, TrainConfig};
use pdt_rundir::OfflineTaskResult;
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
            .map_err(|e| RunError::invalid("a pack's run state", e))
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
                    let _ = self.model.forward(h, Sequence::train(Some(p)).all_steps());
                }
                _ => {
                    let _ = self.model.forward(h, Sequence::train(p));
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
        eval_tasks(self, split, test_time, rng)
    }

    /// The action error of the weights as trained (MT-BC-Finetune's: before any fine-tuning)
    /// on `eval.offline_segments` segments of each task of `split`.
    fn offline_evaluate(
        &mut self,
        split: Split,
        rng: &mut Rng,
    ) -> Result<Option<Vec<OfflineTaskResult>>, RunError> {
        let setup = self.setup;
        let sampler = setup.sampler(setup.data(split))?;
        let (prompted, n) = (self.variant.prompt, setup.cfg.eval.offline_segments);
        let model = &self.model;
        Ok(Some(pdt_eval::offline::action_error(model, &sampler, prompted, n, setup.device, rng)))
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

/// Evaluates the tasks of `split` as `test_time` says, through `pdt_eval::testtime` (the
/// reference rule, a prompt strategy, an `[eval.adapt]` adaptation) or, for MT-BC-Finetune's
/// fine-tuning, this learner's own weights ([`super::finetune`]). An adaptation is of the test
/// tasks; training tasks are evaluated with its strategy alone.
fn eval_tasks(
    learner: &PromptDtLearner<'_>,
    split: Split,
    test_time: &TestTime,
    rng: &mut Rng,
) -> Result<Evaluation, RunError> {
    let setup = learner.setup;
    let settings = eval_settings(setup);
    let ev = split_eval(setup, &learner.model, &learner.vs, &settings, split);
    let on_test = split == Split::Test;
    let done = match test_time {
        TestTime::Adapt { from, adaptation: Adaptation::Prompt(cfg) } if on_test => {
            testtime::evaluate_adapted(&ev, from, cfg, rng)?
        }
        &TestTime::Adapt {
            adaptation: Adaptation::Finetune { steps, batch, lr, data }, ..
        } if on_test => {
            let tune = super::finetune::Finetune { steps, batch, lr, data };
            super::finetune::finetune_each(&learner.vs, &ev, &tune, setup, rng)?
        }
        TestTime::Adapt { adaptation: Adaptation::Macaw { .. }, .. } if on_test => {
            return Err(RunError::invalid(
                "test time",
                format!(
                    "MACAW's adaptation is MACAW's own; this run is {}",
                    setup.cfg.run.method.name()
                ),
            ))
        }
        TestTime::Strategy(s) | TestTime::Adapt { from: s, .. } if !s.is_default() => {
            testtime::evaluate_strategy(&ev, s, rng)?
        }
        TestTime::Reference | TestTime::Strategy(_) | TestTime::Adapt { .. } => {
            testtime::evaluate_reference(&ev, rng)?
        }
    };
    let tasks = done.results.into_iter().map(|result| TaskEval { result, adaptation: None });
    Ok(Evaluation { tasks: tasks.collect(), picks: done.picks, adapt_log: done.adapt_log })
}

/// The settings of the run's evaluations.
fn eval_settings(setup: &Setup) -> EvalSettings {
    EvalSettings {
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
    }
}

/// What an evaluation of `split` needs of the run, for `pdt_eval::testtime`.
fn split_eval<'a>(
    setup: &'a Setup,
    model: &'a PromptDt,
    weights: &'a VarStore,
    settings: &'a EvalSettings,
    split: Split,
) -> SplitEval<'a> {
    let rd = &setup.run_data;
    SplitEval {
        model,
        // Full fine-tuning's: changed per test task and restored after its episodes.
        weights: Some(weights),
        settings,
        data: setup.data(split),
        sampler_cfg: &rd.sampler_cfg,
        norm: &rd.norm,
        n_positions: rd.model_cfg.n_positions,
        method: setup.cfg.run.method,
        episodes: setup.cfg.eval.episodes,
        family: setup.family.as_ref(),
        run_target_set: setup.cfg.eval.target_return.is_some(),
    }
}

/// The error of a non-finite loss or gradient: the step, the values and the likely causes.
fn diverged(dir: &Path, cfg: &TrainConfig, iteration: u64, step: u64, st: &StepStats) -> RunError {
    RunError::Diverged {
        dir: dir.into(),
        message: format!(
            "training diverged at iteration {iteration}, gradient step {step}: loss {}, gradient \
         norm {}. Likely causes: optim.learning_rate = {} too high, optim.eps = {} too small, or \
         extreme values in the data (data.dir {}). Resuming would repeat the same steps: fix the \
         configuration and train again.",
            compact(st.loss),
            compact(st.grad_norm),
            compact(cfg.optim.learning_rate),
            compact(cfg.optim.eps),
            cfg.data.dir.display()
        ),
    }
}
