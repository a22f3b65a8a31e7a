//! [`BatchedEngine`]: a pack's runs as one batched model ([`crate::model`]) with a packed
//! AdamW (`optim`): one forward, one backward and one optimiser pass for all runs of a step.
//!
//! The shapes of every step are fixed for the pack's life ([`PackLayout`]): a run without inputs in
//! a step is computed on a finite placeholder and its results dropped, so that a run's results do
//! not depend on which other runs are stepped (the first point of the [`PackEngine`] contract; a
//! matrix product's kernel may depend on its batch count). Call [`PackEngine::step`] and
//! [`BatchedEngine::new`] with libtorch's generator held (`pdt_train::streams::torch_rng_lock`), as
//! the solo learner is called.

mod optim;

use crate::engine::{PackEngine, SlotSpec, SlotStep};
use crate::model::{
    DropoutSeeds, LayerNormPlan, MaskDraw, PackedBatch, PackedError, PackedPromptDt, PackedRow,
};
use optim::PackedAdamW;
use pdt_base::seed::derive_seed;
use pdt_model::prompt_dt::Sequence;
use pdt_model::{PromptDt, PromptDtConfig, Segments};
use pdt_run::streams::{STREAM_DROPOUT, STREAM_INIT};
use pdt_rundir::config::LossOn;
use pdt_train::optim::SlotState;
use pdt_train::run::RunError;
use pdt_train::step::PendingStats;
use std::collections::BTreeSet;
use tch::{nn::VarStore, Device, Kind, Tensor};

/// The shapes of every step's batches, fixed for the pack's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackLayout {
    /// Samples per batch (every run's `train.batch_size`).
    pub batch_size: usize,
    /// History steps K (every run's).
    pub history_len: usize,
    /// The longest prompt of the pack's runs in steps (J x H; 0 when no run uses a prompt).
    /// Shorter prompts, and runs without one, are padded to it.
    pub prompt_len: usize,
}

/// Steps every run of a pack with one batched computation.
#[derive(Debug)]
pub struct BatchedEngine {
    specs: Vec<SlotSpec>,
    layout: PackLayout,
    model: PackedPromptDt,
    opt: PackedAdamW,
    /// Per run, 1 where its loss reads its prompt's steps, else 0: `[N]` on the device (the specs
    /// fix it for the pack's life).
    supervise: Tensor,
    /// The patterns of stepped runs.
    active: pdt_torch::device::BoolUploads,
}

fn invalid(e: PackedError) -> RunError {
    RunError::invalid("pack", e)
}

impl BatchedEngine {
    /// A pack of `specs.len()` runs on `device`, each slot initialised as its solo run is (libtorch's
    /// generator seeded with `derive_seed(seed, STREAM_INIT, 0)`, then `PromptDt::new`), with empty
    /// moments. Every run must have the same model configuration.
    pub fn new(specs: Vec<SlotSpec>, layout: PackLayout, device: Device) -> Result<Self, RunError> {
        let first = specs.first().ok_or_else(|| RunError::invalid("pack", "no runs"))?;
        let cfg = first.model.clone();
        cfg.validate().map_err(|e| RunError::invalid("pack", e))?;
        if let Some((i, _)) = specs.iter().enumerate().find(|(_, s)| s.model != cfg) {
            return Err(RunError::invalid(
                "pack",
                format!(
                    "run {i}'s model configuration differs from run 0's (a pack shares one shape)"
                ),
            ));
        }
        let (p, k) = (layout.prompt_len, layout.history_len);
        if specs.iter().any(|s| s.uses_prompt) && p == 0 {
            return Err(RunError::invalid("pack", "a run uses a prompt, layout.prompt_len is 0"));
        }
        if layout.batch_size == 0 || k == 0 || 3 * (p + k) > cfg.n_positions {
            return Err(RunError::invalid(
                "pack",
                format!(
                    "layout {layout:?} (3 x (prompt + history) tokens must fit n_positions = {})",
                    cfg.n_positions
                ),
            ));
        }
        let mut model = PackedPromptDt::new(&cfg, specs.len(), device).map_err(invalid)?;
        // `train.last_block` (`auto`: the state tokens), one for the pack's computation.
        let last = pdt_train::step::last_block(first.last_block, device, true);
        if let Some((i, s)) = specs
            .iter()
            .enumerate()
            .find(|(_, s)| pdt_train::step::last_block(s.last_block, device, true) != last)
        {
            return Err(RunError::invalid(
                "pack",
                format!(
                    "run {i}'s train.last_block ({}) differs from run 0's ({})",
                    s.last_block.as_str(),
                    first.last_block.as_str()
                ),
            ));
        }
        model.set_last_block(last);
        // Which parameters each run's loss reads, as its solo model says (one set with a prompt,
        // one without): a parameter a run never reads gets no update and no step count.
        let reads = [false, true].map(|p| read_parameters(&cfg, p, device));
        for (slot, spec) in specs.iter().enumerate() {
            tch::manual_seed(derive_seed(spec.seed, STREAM_INIT, 0) as i64);
            let vs = VarStore::new(device);
            let _solo = PromptDt::new(&vs.root(), &cfg);
            let vars = vs.variables();
            let weights: Vec<(String, Tensor)> = model
                .names()
                .iter()
                .filter_map(|n| vars.get(n).map(|t| (n.clone(), t.shallow_clone())))
                .collect();
            model.set_slot(slot, &weights).map_err(invalid)?;
        }
        let used = model
            .names()
            .iter()
            .map(|name| specs.iter().map(|s| reads[usize::from(s.uses_prompt)].contains(name)))
            .map(Iterator::collect)
            .collect();
        let cfgs = specs.iter().map(|s| s.optim.clone()).collect();
        // Flat when every run's `optim.flat` asks for it on this device (`auto`: on CUDA).
        let flat = specs.iter().all(|s| s.optim.flat.use_flat(device.is_cuda()));
        let opt = PackedAdamW::new(model.names(), model.weights(), cfgs, used, device, flat);
        // As `pdt_train::step::train_step`: the prompt's steps are supervised only with
        // `LossOn::PromptAndHistory` and a prompt.
        let supervise: Vec<f32> = specs
            .iter()
            .map(|s| f32::from(u8::from(s.uses_prompt && s.loss_on == LossOn::PromptAndHistory)))
            .collect();
        let supervise = pdt_torch::device::upload(&supervise, device);
        Ok(Self { specs, layout, model, opt, supervise, active: Default::default() })
    }

    pub fn layout(&self) -> PackLayout {
        self.layout
    }

    /// The batched model (its stacked weights; for tests and measurements).
    pub fn model(&self) -> &PackedPromptDt {
        &self.model
    }

    /// Whether the optimiser runs on flat buffers (every run's `optim.flat` on this device).
    pub fn is_flat(&self) -> bool {
        self.opt.is_flat()
    }

    /// How dropout masks are drawn (default: [`MaskDraw::default_for`] the pack's device).
    pub fn set_mask_draw(&mut self, draw: MaskDraw) {
        self.model.set_mask_draw(draw);
    }

    /// How the batched model computes its LayerNorms (default: by the device; for measurements).
    pub fn set_layer_norm(&mut self, plan: LayerNormPlan) {
        self.model.set_layer_norm(plan);
    }

    fn check_slot(&self, slot: usize) -> Result<(), RunError> {
        if slot >= self.specs.len() {
            return Err(invalid(PackedError::Slot { slot, slots: self.specs.len() }));
        }
        Ok(())
    }
}

impl PackEngine for BatchedEngine {
    fn slots(&self) -> usize {
        self.specs.len()
    }

    fn step(
        &mut self,
        steps: Vec<Option<SlotStep>>,
    ) -> Result<Vec<Option<PendingStats>>, RunError> {
        let n = self.specs.len();
        if steps.len() != n {
            return Err(RunError::Internal(format!(
                "pack: {} slot steps for a pack of {n} runs",
                steps.len()
            )));
        }
        let active: Vec<bool> = steps.iter().map(Option::is_some).collect();
        if !active.iter().any(|&a| a) {
            return Ok((0..n).map(|_| None).collect());
        }
        for (slot, (st, spec)) in steps.iter().zip(&self.specs).enumerate() {
            let Some(st) = st else { continue };
            if st.batch.prompt.is_some() != spec.uses_prompt {
                return Err(RunError::Internal(format!(
                    "pack: run {slot} {}, its batch {}",
                    if spec.uses_prompt { "uses a prompt" } else { "uses no prompt" },
                    if st.batch.prompt.is_some() { "has one" } else { "has none" }
                )));
            }
        }
        let rows: Vec<Option<PackedRow<'_>>> = steps
            .iter()
            .map(|s| {
                s.as_ref().map(|s| PackedRow {
                    history: &s.batch.history,
                    prompt: s.batch.prompt.as_ref(),
                })
            })
            .collect();
        let l = &self.layout;
        let batch = PackedBatch::new(
            &rows,
            l.batch_size as i64,
            l.history_len as i64,
            l.prompt_len as i64,
            &self.model.cfg,
            self.model.device(),
        )
        .map_err(invalid)?;
        let seeds = DropoutSeeds(
            steps
                .iter()
                .zip(&self.specs)
                .map(|(s, spec)| {
                    s.as_ref().map(|s| derive_seed(spec.seed, STREAM_DROPOUT, s.step) as i64)
                })
                .collect(),
        );
        // The one-dimensional parameters read through views bound once per weight storage (made
        // again only after the optimiser re-points a weight): fewer operators per step.
        self.model.bind_broadcast();
        let preds = self.model.forward_all_steps(&batch, Some(&seeds)); // [N, B, P+K, da]

        let (targets, mask) = batch.targets(&self.supervise);
        let loss = PackedPromptDt::action_loss(&preds, &targets, &mask); // [N]
        let device = self.model.device();
        let active_t = self.active.get(&active, device);
        // A run not stepped gets no gradient (`where`, so its placeholder cannot send a NaN).
        let total = loss.where_scalarother(&active_t, 0.0).sum(Kind::Float);
        // (A bound view's gradient is `[N, 1, d]`, its weight's shape with a unit dimension: the
        // optimiser reads it at the weight's shape.)
        let inputs = self.model.grad_inputs();
        let grads: Vec<Option<Tensor>> = Tensor::run_backward(&[total], &inputs, false, false)
            .into_iter()
            .map(|g| g.defined().then_some(g))
            .collect();
        let lrs: Vec<f64> = steps
            .iter()
            .zip(&self.specs)
            .map(|(s, spec)| s.as_ref().map_or(0.0, |s| spec.optim.lr_at(s.step)))
            .collect();
        let norms = self.opt.step(self.model.weights(), &grads, &active, &lrs); // [N]

        // Every run's loss and norm left on the device: each run reads its own column with its
        // iteration's other steps (`PendingStats::read_all`), so the host goes on to the next
        // step while the device computes this one.
        let stats = Tensor::stack(&[loss.detach(), norms], 0); // [2, N]
        Ok((0..n).map(|s| active[s].then(|| PendingStats::column(&stats, s, lrs[s]))).collect())
    }

    fn export(&self, slot: usize) -> Result<SlotState, RunError> {
        self.check_slot(slot)?;
        let weights = self.model.slot_weights(slot).map_err(invalid)?;
        Ok(SlotState { weights, moments: self.opt.export(slot) })
    }

    fn import(&mut self, slot: usize, state: SlotState) -> Result<(), RunError> {
        self.check_slot(slot)?;
        self.model.set_slot(slot, &state.weights).map_err(invalid)?;
        self.opt
            .import(slot, &state.moments)
            .map_err(|e| RunError::invalid(format!("pack: run {slot}"), e))
    }
}

/// The parameters of a solo model of `cfg` to which its action loss gives a gradient, with a
/// prompt or without (PyTorch's non-`None` gradients, which its AdamW steps): read off one
/// backward of the solo model on a placeholder batch, so that no parameter is named here (the
/// unused token embedding and state and return heads get none; the prompt layers only with a
/// prompt). Draws from libtorch's generator (the model's initialisation): call it with the
/// generator held, before the runs' own initialisations are drawn.
fn read_parameters(cfg: &PromptDtConfig, uses_prompt: bool, device: Device) -> BTreeSet<String> {
    let vs = VarStore::new(device);
    let model = PromptDt::new(&vs.root(), cfg);
    let (ds, da) = (cfg.state_dim, cfg.act_dim);
    let one = |t: usize| {
        let (s, a) = (vec![0f32; t * ds], vec![0f32; t * da]);
        let (rtg, ts, mask) = (vec![0f32; t], vec![0i64; t], vec![1f32; t]);
        Segments::from_host(1, t, ds, da, &s, &a, &rtg, &ts, &mask, device)
    };
    let prompt = uses_prompt.then(|| one(1));
    model.forward(&one(1), Sequence::eval(prompt.as_ref())).sum(Kind::Float).backward();
    vs.variables().into_iter().filter(|(_, t)| t.grad().defined()).map(|(n, _)| n).collect()
}
