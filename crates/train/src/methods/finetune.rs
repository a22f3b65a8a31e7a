//! MT-BC-Finetune's test time (`Adaptation::Finetune`): before each test task's episodes, a copy
//! of every weight fine-tuned on the task's demonstrations. An adaptation of the learner's own
//! weights, so carried out here, with the weights and the optimiser that trained them; the tasks
//! are planned and evaluated as every test time's are (`pdt_eval::testtime`).

use crate::error::RunError;
use crate::optim::Optimizer;
use crate::setup::Setup;
use crate::step::{train_step, unreadable, DeviceBatch};
use pdt_eval::testtime::{summarise_plans, SplitEval, SplitResult};
use pdt_prompt::Rng;
use pdt_rundir::config::{AdamWConfig, FinetuneData, LossOn};
use tch::{nn::VarStore, Tensor};

/// The fine-tuning before each test task: its steps, segments per step and learning rate.
pub(super) struct Finetune {
    pub(super) steps: u64,
    pub(super) batch: usize,
    pub(super) lr: f64,
    /// What each step's segments come from: the task's main dataset (the reference) or its
    /// demonstrations (`eval.finetune_data = "prompts"`).
    pub(super) data: FinetuneData,
}

/// Per task of `ev` (the test split; `vs` holds `ev.model`'s weights): plans the task as the
/// reference does, adapts a copy of the weights on its demonstrations with a fresh optimiser,
/// evaluates, restores. (The reference shares one optimiser across the test tasks of an
/// evaluation, leaking Adam moments between them: pitfall 13, fixed here.) Planning and tuning
/// draw from `rng` task by task, in that order.
pub(super) fn finetune_each(
    vs: &VarStore,
    ev: &SplitEval<'_>,
    tune: &Finetune,
    setup: &Setup,
    rng: &mut Rng,
) -> Result<SplitResult, RunError> {
    let sampler = ev.reference_sampler()?;
    let snapshot: Vec<(String, Tensor)> =
        vs.variables().into_iter().map(|(n, t)| (n, t.copy())).collect();
    let mut results = Vec::new();
    for i in 0..ev.data.tasks.len() {
        let plan = ev.plan(&sampler, i, rng);
        let task = ev.task(&plan, &plan.seeds, plan.prompt.clone());
        let ocfg =
            AdamWConfig { learning_rate: tune.lr, warmup_steps: 1, ..setup.cfg.optim.clone() };
        let mut opt = Optimizer::new(vs, &setup.run_data.model_cfg.parameter_names(), ocfg);
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
            let history = pdt_eval::to_segments(&seg, setup.device);
            let batch = DeviceBatch { history, prompt: None };
            train_step(ev.model, &mut opt, &batch, LossOn::History, s).map_err(unreadable)?;
        }
        let eps = ev.evaluate(ev.model, vec![task], None, None)?;
        results.extend(summarise_plans(std::slice::from_ref(&plan), &eps));
        tch::no_grad(|| {
            let vars = vs.variables();
            for (n, saved) in &snapshot {
                if let Some(v) = vars.get(n) {
                    v.shallow_clone().copy_(saved);
                }
            }
        });
    }
    Ok(SplitResult { results, ..Default::default() })
}
