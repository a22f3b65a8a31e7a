//! Pack cases: `pack<N>_b<B>` times one gradient step of N runs trained as one pack
//! (`pdt_train::pack::BatchedEngine`), `solo<N>_b<B>` the same N runs' steps one after another in
//! one process (N models, N optimisers): per iteration, one step of every run. The reference
//! architecture (state 20, action 6), K = 20, a 5-step prompt, B samples per run; each run its own
//! random batch, left-padded histories. Both use what a run uses on the device (`optim.flat =
//! "auto"`: the flat optimisers and per-run mask draws on CUDA, the per-tensor ones on the CPU);
//! the suffix `_flat` asks for the CUDA configuration on any device (`optim.flat = "on"`, the
//! pack's masks drawn per run, one LayerNorm for the pack, a solo run's last block for the state
//! tokens only), `_pt` for the CPU one (`optim.flat = "off"`, masks in solo order, a LayerNorm per
//! run, a solo run's last block on every token). A pack's last block always runs for the state
//! tokens only. A final `_mix` gives every second run no prompt (as Figure 2's pack of 4 methods,
//! whose MT-ORL and MT-BC-Finetune runs have none), the others a prompt as before.
//!
//! With `_act` a case times one environment step of N runs evaluating with B episodes each: the
//! pack's forward for all runs (`pack<N>_b<B>_act`: `PackEngine::act`, as `--pack-eval together`)
//! against each run's own cached forward in turn (`solo<N>_b<B>_act`: `PromptDt::act` with its
//! tasks' prompt prefix, as `--pack-eval apart`), the actions copied to the host in both.

use crate::random_segments;
use pdt_base::seed::derive_seed;
use pdt_model::packed::{LayerNormPlan, MaskDraw};
use pdt_model::{LastBlock, PrefixCache, PromptDt, PromptDtConfig, Segments};
use pdt_train::optim::{AdamWConfig, FlatOptim, Optimizer};
use pdt_train::pack::{BatchedEngine, PackEngine, PackLayout, SlotAct, SlotSpec, SlotStep};
use pdt_train::step::{train_step_with, DeviceBatch, LossOn};
use std::time::Instant;
use tch::{nn::VarStore, Device, Kind, Tensor};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PackMode {
    /// One `BatchedEngine` step for all runs.
    Packed,
    /// One `train_step` per run, in turn.
    Solo,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackCase {
    pub mode: PackMode,
    pub runs: usize,
    pub batch: usize,
    /// `optim.flat` (`_flat`: on, `_pt`: off, no suffix: auto).
    pub flat: FlatOptim,
    /// `_act`: an evaluation's forward, not a gradient step.
    pub act: bool,
    /// `_mix`: the odd-numbered runs without a prompt.
    pub mix: bool,
}

/// `pack<N>_b<B>` or `solo<N>_b<B>` (N, B at least 1), then `_flat`, `_pt` or `_act` if wanted,
/// then `_mix` if wanted (not with `_act`).
pub fn parse_case(name: &str) -> Option<PackCase> {
    let (name, mix) = match name.strip_suffix("_mix") {
        Some(r) => (r, true),
        None => (name, false),
    };
    let (name, act) = match name.strip_suffix("_act") {
        Some(r) => (r, true),
        None => (name, false),
    };
    let (mode, rest) = if let Some(r) = name.strip_prefix("pack") {
        (PackMode::Packed, r)
    } else {
        (PackMode::Solo, name.strip_prefix("solo")?)
    };
    let (rest, flat) = if let Some(r) = rest.strip_suffix("_flat") {
        (r, FlatOptim::On)
    } else if let Some(r) = rest.strip_suffix("_pt") {
        (r, FlatOptim::Off)
    } else {
        (rest, FlatOptim::Auto)
    };
    let (runs, batch) = rest.split_once("_b")?;
    let runs = runs.parse().ok().filter(|&n: &usize| n > 0)?;
    let batch = batch.parse().ok().filter(|&b: &usize| b > 0)?;
    if act && (flat != FlatOptim::Auto || mix) {
        return None; // an evaluation's forward has no optimiser; its runs all have prompts
    }
    Some(PackCase { mode, runs, batch, flat, act, mix })
}

const K: usize = 20;
const PROMPT: usize = 5;

/// Milliseconds per iteration (one step of every run), `iters` timed after `warmup`.
pub fn time_pack(
    case: PackCase,
    warmup: usize,
    iters: usize,
    device: Device,
) -> Result<Vec<f64>, String> {
    if case.act {
        return time_act(case, warmup, iters, device);
    }
    let cfg = PromptDtConfig::reference(20, 6);
    let (b, k, p) = (case.batch as i64, K as i64, PROMPT as i64);
    tch::manual_seed(0);
    let batches: Vec<(Segments, Segments)> = (0..case.runs)
        .map(|_| {
            (
                random_segments(b, k, 20, 6, false, device),
                random_segments(b, p, 20, 6, true, device),
            )
        })
        .collect();
    let prompted = |i: usize| !(case.mix && i % 2 == 1);
    let batch_of = |i: usize| DeviceBatch {
        history: batches[i].0.shallow_clone(),
        prompt: prompted(i).then(|| batches[i].1.shallow_clone()),
    };
    type StepFn<'a> = Box<dyn FnMut(u64) -> Result<(), String> + 'a>;
    let optim = AdamWConfig { flat: case.flat, ..AdamWConfig::default() };
    let step_fn: StepFn<'_> = match case.mode {
        PackMode::Packed => {
            let mut specs = specs(case.runs, &cfg, &optim);
            for (i, s) in specs.iter_mut().enumerate() {
                s.uses_prompt = prompted(i);
            }
            let layout = PackLayout { batch_size: case.batch, history_len: K, prompt_len: PROMPT };
            let mut engine =
                BatchedEngine::new(specs, layout, device).map_err(|e| e.to_string())?;
            // The mask draw and the LayerNorms go with the optimiser's configuration (`_flat`:
            // CUDA's, so that `--profile` counts on a CPU what a GPU step launches).
            let cuda_like = case.flat.use_flat(device.is_cuda());
            engine.set_mask_draw(if cuda_like { MaskDraw::PerRun } else { MaskDraw::SoloOrder });
            engine.set_layer_norm(if cuda_like {
                LayerNormPlan::Batched
            } else {
                LayerNormPlan::PerRun
            });
            Box::new(move |step| {
                let steps =
                    (0..case.runs).map(|i| Some(SlotStep { step, batch: batch_of(i) })).collect();
                engine.step(steps).map(|_| ()).map_err(|e| e.to_string())
            })
        }
        PackMode::Solo => {
            let mut runs: Vec<(VarStore, PromptDt, Optimizer)> = (0..case.runs as u64)
                .map(|seed| {
                    tch::manual_seed(derive_seed(seed, 1, 0) as i64);
                    let vs = VarStore::new(device);
                    let mut model = PromptDt::new(&vs.root(), &cfg);
                    // The last block as the optimiser's configuration has it (`_flat`: CUDA's).
                    model.set_last_block(if case.flat.use_flat(device.is_cuda()) {
                        LastBlock::StateTokens
                    } else {
                        LastBlock::AllTokens
                    });
                    // The optimiser a solo run uses here (flat on CUDA).
                    let opt = Optimizer::new(&vs, &cfg.parameter_names(), optim.clone());
                    (vs, model, opt)
                })
                .collect();
            Box::new(move |step| {
                for (i, (_, model, opt)) in runs.iter_mut().enumerate() {
                    // As the solo learner: dropout re-seeded per run and step.
                    tch::manual_seed(derive_seed(i as u64, 3, step) as i64);
                    // Its statistics not read, as the solo loop reads an iteration's at its end
                    // (this bench waits for the device after each step).
                    let draw = pdt_model::dropout::Dropout::Draw;
                    let _ = train_step_with(model, opt, &batch_of(i), LossOn::History, step, draw);
                }
                Ok(())
            })
        }
    };
    timed(warmup, iters, device, step_fn)
}

/// Milliseconds per environment step of `case.runs` runs evaluating `case.batch` episodes each
/// (their actions on the host), `iters` timed after `warmup`.
fn time_act(
    case: PackCase,
    warmup: usize,
    iters: usize,
    device: Device,
) -> Result<Vec<f64>, String> {
    let cfg = PromptDtConfig::reference(20, 6);
    let (b, k, p) = (case.batch as i64, K as i64, PROMPT as i64);
    tch::manual_seed(0);
    // Each run's histories and its episodes' task prompts (2 tasks, as Cheetah-Dir's test split).
    let histories: Vec<Segments> =
        (0..case.runs).map(|_| random_segments(b, k, 20, 6, false, device)).collect();
    let tasks: Vec<Segments> =
        (0..case.runs).map(|_| random_segments(2, p, 20, 6, true, device)).collect();
    let rows = Tensor::arange(b, (Kind::Int64, device)).remainder(2);
    let prompt_of = |i: usize| -> Segments {
        let t = &tasks[i];
        Segments {
            states: t.states.index_select(0, &rows),
            actions: t.actions.index_select(0, &rows),
            returns_to_go: t.returns_to_go.index_select(0, &rows),
            timesteps: t.timesteps.index_select(0, &rows),
            mask: t.mask.index_select(0, &rows),
        }
    };
    let prompts: Vec<Segments> = (0..case.runs).map(prompt_of).collect();
    type ActFn<'a> = Box<dyn FnMut() -> Result<(), String> + 'a>;
    let mut act_fn: ActFn<'_> = match case.mode {
        PackMode::Packed => {
            let specs = specs(case.runs, &cfg, &AdamWConfig::default());
            let layout = PackLayout { batch_size: case.batch, history_len: K, prompt_len: PROMPT };
            let mut engine =
                BatchedEngine::new(specs, layout, device).map_err(|e| e.to_string())?;
            Box::new(move || {
                let acts = (0..case.runs)
                    .map(|i| {
                        Some(SlotAct {
                            history: histories[i].shallow_clone(),
                            prompt: Some(prompts[i].shallow_clone()),
                            rows: b,
                        })
                    })
                    .collect();
                let out = engine.act(acts).map_err(|e| e.to_string())?;
                // Each run's evaluation copies its own actions to the host.
                for a in out.into_iter().flatten() {
                    let _ = a.to_device(Device::Cpu);
                }
                Ok(())
            })
        }
        PackMode::Solo => {
            let runs: Vec<(VarStore, PromptDt, PrefixCache)> = (0..case.runs)
                .map(|i| {
                    tch::manual_seed(derive_seed(i as u64, 1, 0) as i64);
                    let vs = VarStore::new(device);
                    let model = PromptDt::new(&vs.root(), &cfg);
                    // As in an evaluation: the tasks' prompt keys and values once.
                    let cache = tch::no_grad(|| model.prefix(&tasks[i]));
                    (vs, model, cache)
                })
                .collect();
            Box::new(move || {
                for (i, (_, model, cache)) in runs.iter().enumerate() {
                    let a = tch::no_grad(|| model.act(&histories[i], Some(&cache.select(&rows))));
                    let _ = a.to_device(Device::Cpu);
                }
                Ok(())
            })
        }
    };
    timed(warmup, iters, device, |_| act_fn())
}

/// The reference-shaped runs of a pack case, seeds 0.., each with a prompt.
fn specs(runs: usize, cfg: &PromptDtConfig, optim: &AdamWConfig) -> Vec<SlotSpec> {
    (0..runs as u64)
        .map(|seed| SlotSpec {
            model: cfg.clone(),
            uses_prompt: true,
            loss_on: LossOn::History,
            optim: optim.clone(),
            last_block: pdt_train::step::LastBlockChoice::Auto,
            seed,
        })
        .collect()
}

/// Milliseconds of each of `iters` calls of `f` (given its call index) after `warmup` untimed
/// ones, the device's queue drained before each time is read.
fn timed(
    warmup: usize,
    iters: usize,
    device: Device,
    mut f: impl FnMut(u64) -> Result<(), String>,
) -> Result<Vec<f64>, String> {
    let sync = || {
        if let Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
    };
    for s in 0..warmup {
        f(s as u64)?;
    }
    sync();
    (0..iters)
        .map(|s| {
            let t0 = Instant::now();
            f((warmup + s) as u64)?;
            sync();
            Ok(t0.elapsed().as_secs_f64() * 1e3)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pack_case_names() {
        let c = |m, runs, batch| PackCase {
            mode: m,
            runs,
            batch,
            flat: FlatOptim::Auto,
            act: false,
            mix: false,
        };
        assert_eq!(parse_case("pack3_b64"), Some(c(PackMode::Packed, 3, 64)));
        assert_eq!(parse_case("solo12_b16"), Some(c(PackMode::Solo, 12, 16)));
        let flat = PackCase { flat: FlatOptim::On, ..c(PackMode::Packed, 12, 32) };
        assert_eq!(parse_case("pack12_b32_flat"), Some(flat));
        let pt = PackCase { flat: FlatOptim::Off, ..c(PackMode::Solo, 1, 8) };
        assert_eq!(parse_case("solo1_b8_pt"), Some(pt));
        let act = PackCase { act: true, ..c(PackMode::Packed, 12, 100) };
        assert_eq!(parse_case("pack12_b100_act"), Some(act));
        assert_eq!(parse_case("solo12_b100_act"), Some(PackCase { mode: PackMode::Solo, ..act }));
        let mix = PackCase { mix: true, ..flat };
        assert_eq!(parse_case("pack12_b32_flat_mix"), Some(mix));
        assert_eq!(
            parse_case("solo12_b32_flat_mix"),
            Some(PackCase { mode: PackMode::Solo, ..mix })
        );
        for bad in [
            "pack0_b64",
            "pack3_b0",
            "pack3",
            "solo_b4",
            "packx_b2",
            "train_b64",
            "pack3_b2_x",
            "pack3_b2_flat_act",
            "pack3_b2_act_flat",
            "pack3_b2_act_mix",
            "pack3_b2_mix_flat",
        ] {
            assert_eq!(parse_case(bad), None, "{bad}");
        }
    }
}
