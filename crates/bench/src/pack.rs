//! Pack cases: `pack<N>_b<B>` times one gradient step of N runs trained as one pack
//! (`pdt_pack::BatchedEngine`), `solo<N>_b<B>` the same N runs' steps one after another in
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

use crate::random_segments;
use pdt_base::seed::derive_seed;
use pdt_model::{LastBlock, PromptDt, PromptDtConfig, Segments};
use pdt_pack::model::{LayerNormPlan, MaskDraw};
use pdt_pack::{BatchedEngine, PackEngine, PackLayout, SlotSpec, SlotStep};
use pdt_rundir::config::LossOn;
use pdt_rundir::config::{AdamWConfig, FlatOptim};
use pdt_train::optim::Optimizer;
use pdt_train::step::{train_step_with, DeviceBatch};
use std::time::Instant;
use tch::{nn::VarStore, Device};

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
    /// `_mix`: the odd-numbered runs without a prompt.
    pub mix: bool,
}

/// `pack<N>_b<B>` or `solo<N>_b<B>` (N, B at least 1), then `_flat` or `_pt` if wanted, then
/// `_mix` if wanted.
pub fn parse_case(name: &str) -> Option<PackCase> {
    let (name, mix) = match name.strip_suffix("_mix") {
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
    Some(PackCase { mode, runs, batch, flat, mix })
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

/// The reference-shaped runs of a pack case, seeds 0.., each with a prompt.
fn specs(runs: usize, cfg: &PromptDtConfig, optim: &AdamWConfig) -> Vec<SlotSpec> {
    (0..runs as u64)
        .map(|seed| SlotSpec {
            model: cfg.clone(),
            uses_prompt: true,
            loss_on: LossOn::History,
            optim: optim.clone(),
            last_block: pdt_rundir::config::LastBlockChoice::Auto,
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
        let c =
            |m, runs, batch| PackCase { mode: m, runs, batch, flat: FlatOptim::Auto, mix: false };
        assert_eq!(parse_case("pack3_b64"), Some(c(PackMode::Packed, 3, 64)));
        assert_eq!(parse_case("solo12_b16"), Some(c(PackMode::Solo, 12, 16)));
        let flat = PackCase { flat: FlatOptim::On, ..c(PackMode::Packed, 12, 32) };
        assert_eq!(parse_case("pack12_b32_flat"), Some(flat));
        let pt = PackCase { flat: FlatOptim::Off, ..c(PackMode::Solo, 1, 8) };
        assert_eq!(parse_case("solo1_b8_pt"), Some(pt));
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
            "pack12_b100_act",
            "pack3_b2_mix_flat",
        ] {
            assert_eq!(parse_case(bad), None, "{bad}");
        }
    }
}
