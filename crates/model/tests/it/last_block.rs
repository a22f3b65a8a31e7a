//! `LastBlock::StateTokens` (the last block for the state tokens only, the CUDA default) against
//! `LastBlock::AllTokens` (the reference's ops, the CPU default): the same predictions and
//! gradients within float rounding, in eval mode and in train mode with the same dropout masks,
//! given or drawn.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::support;
use pdt_model::dropout::{Dropout, DropoutMasks};
use pdt_model::prompt_dt::Sequence;
use pdt_model::{LastBlock, PromptDt, PromptDtConfig};
use support::segments;
use tch::{nn::VarStore, Device, Kind, Tensor};

// libtorch's generator is global: the tests that seed it take turns (with the other modules'
// tests: one lock for the test binary).
use pdt_testkit::process::LIBTORCH as RNG;

fn cfg() -> PromptDtConfig {
    // Two heads, so that the attention's reshapes of the state rows are exercised.
    PromptDtConfig { n_head: 2, ..PromptDtConfig::reference(5, 3) }
}

struct Outcome {
    preds: Tensor,
    grads: Vec<(String, Tensor)>,
}

/// Predictions at every step and the gradients of their masked squared error, for one setting.
fn run(last: LastBlock, prompt: bool, train: bool) -> Outcome {
    tch::manual_seed(7);
    let vs = VarStore::new(Device::Cpu);
    let mut model = PromptDt::new(&vs.root(), &cfg());
    assert_eq!(
        model.last_block(),
        LastBlock::AllTokens,
        "the CPU default keeps the reference's ops"
    );
    model.set_last_block(last);
    let history = segments(6, 20, 5, 3);
    let prompt = prompt.then(|| segments(6, 5, 5, 3));
    let len = PromptDt::token_count(&history, prompt.as_ref());
    let masks = train.then(|| DropoutMasks::draw(&model.cfg, 6, len, Device::Cpu));
    let drop = masks.as_ref().map_or(Dropout::Off, Dropout::Given);
    let preds = model.forward(&history, Sequence::new(prompt.as_ref(), drop).all_steps()); // [B, Lp+K, da]
    let target = Tensor::rand_like(&preds);
    let loss = (&preds - target).pow_tensor_scalar(2).mean(None::<Kind>);
    loss.backward();
    let mut grads: Vec<(String, Tensor)> =
        vs.variables().into_iter().map(|(n, v)| (n, v.grad())).collect();
    grads.sort_by(|a, b| a.0.cmp(&b.0));
    Outcome { preds: preds.detach(), grads }
}

fn max_abs(a: &Tensor, b: &Tensor) -> f64 {
    if !a.defined() || !b.defined() {
        assert_eq!(a.defined(), b.defined(), "a gradient on one side only");
        return 0.0;
    }
    (a - b).abs().max().double_value(&[])
}

#[test]
fn state_tokens_give_the_full_blocks_predictions_and_gradients() {
    let _g = RNG.lock().unwrap_or_else(|e| e.into_inner());
    let (mut worst_pred, mut worst_grad): (f64, f64) = (0.0, 0.0);
    for prompt in [true, false] {
        for train in [false, true] {
            let full = run(LastBlock::AllTokens, prompt, train);
            let states = run(LastBlock::StateTokens, prompt, train);
            assert_eq!(full.preds.size(), states.preds.size());
            let dp = max_abs(&full.preds, &states.preds);
            let mut dg: f64 = 0.0;
            for ((n, a), (m, b)) in full.grads.iter().zip(&states.grads) {
                assert_eq!(n, m);
                dg = dg.max(max_abs(a, b));
            }
            eprintln!(
                "prompt {prompt}, train {train}: max |pred diff| {dp:e}, max |grad diff| {dg:e}"
            );
            worst_pred = worst_pred.max(dp);
            worst_grad = worst_grad.max(dg);
        }
    }
    // Measured (AMD EPYC, AVX2 kernels, libtorch 2.11): predictions 0, gradients at most 1.1e-8
    // (the weight gradients of the last block sum a product of fewer rows, in another order).
    // Predictions are O(0.1): a mask read at the wrong rows would differ by that much. Bounds
    // ~20x the gradients' measurement; 1e-6 for predictions (the packs' bound against solo).
    assert!(worst_pred <= 1e-6, "predictions differ by {worst_pred:e}");
    assert!(worst_grad <= 2e-7, "gradients differ by {worst_grad:e}");
}

#[test]
fn drawn_dropout_on_the_cpu_is_the_full_forwards() {
    // Dropout drawn inside the forward (`Dropout::Draw`, a training step's): on the CPU the state
    // tokens' last block draws each site at its full shape and reads it at the state rows, so the
    // masks, the predictions and the generator's state after are the full forward's.
    let _g = RNG.lock().unwrap_or_else(|e| e.into_inner());
    tch::manual_seed(3);
    let vs = VarStore::new(Device::Cpu);
    let mut model = PromptDt::new(&vs.root(), &cfg());
    let (history, prompt) = (segments(4, 20, 5, 3), segments(4, 5, 5, 3));
    let mut run = |last: LastBlock| {
        model.set_last_block(last);
        tch::manual_seed(11);
        let preds =
            tch::no_grad(|| model.forward(&history, Sequence::train(Some(&prompt)).all_steps()));
        let next = Tensor::rand([1], (Kind::Float, Device::Cpu)).double_value(&[0]);
        (preds, next)
    };
    let (full, full_next) = run(LastBlock::AllTokens);
    let (states, states_next) = run(LastBlock::StateTokens);
    assert_eq!(states.size(), [4, 25, 3]);
    let d = max_abs(&full, &states);
    eprintln!("drawn masks: max |pred diff| {d:e}");
    assert!(d <= 1e-6, "predictions differ by {d:e}: other masks?");
    assert_eq!(full_next, states_next, "the generator ends in the same state");
    let eval = tch::no_grad(|| model.forward(&history, Sequence::eval(Some(&prompt)).all_steps()));
    assert!(max_abs(&states, &eval) > 1e-3, "dropout changed nothing");
}

#[test]
fn defaults_per_device() {
    assert_eq!(LastBlock::default_for(Device::Cpu), LastBlock::AllTokens);
    assert_eq!(LastBlock::default_for(Device::Cuda(0)), LastBlock::StateTokens);
}
