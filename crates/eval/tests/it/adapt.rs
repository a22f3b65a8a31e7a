//! The evaluation-time adaptations (`pdt_eval::testtime::adapt`) on a small model and a fixed
//! demonstration set: each moves the demonstrations' action loss down; LoRA at step 0 is the
//! frozen model bit for bit; the zeroth-order update prefers the better candidate; full
//! fine-tuning changes the weights, reproducibly from the seed, and with 0 steps leaves them as
//! they are.
#![allow(clippy::unwrap_used, clippy::expect_used)] // test code

use pdt_eval::testtime::adapt::{self, demo_loss, rank_direction, ActionLossScore, PromptScore};
use pdt_eval::{prompt_batch, to_vec, EvalError};
use pdt_model::prompt_dt::{Act, Prompt, Sequence};
use pdt_model::{LastBlock, PromptDt, PromptDtConfig, Segments};
use pdt_prompt::{Rng, SegmentBatch};
use pdt_rundir::config::{AdaptConfig, AdaptKind};
use rand::{Rng as _, SeedableRng};
use tch::nn::VarStore;
use tch::Device;

const DS: usize = 3;
const DA: usize = 2;
const K: usize = 5;
const LP: usize = 4;

// libtorch's generator is global: tests that seed it and build a model take turns (with the
// other modules' tests: one lock for the test binary).
use pdt_testkit::process::LIBTORCH as TORCH_RNG;

fn model() -> (VarStore, PromptDt) {
    let _turn = TORCH_RNG.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    tch::manual_seed(7);
    let vs = VarStore::new(Device::Cpu);
    let cfg = PromptDtConfig {
        hidden_size: 16,
        n_layer: 2,
        n_head: 1,
        n_inner: 64,
        max_ep_len: 100,
        n_positions: 128,
        ..PromptDtConfig::reference(DS, DA)
    };
    let m = PromptDt::new(&vs.root(), &cfg);
    // GPT-2's init (std 0.02) leaves a fresh model's attention nearly blind to the prompt: its
    // output is a small addition to the residual. Scaled up, the prompt matters, as it does in
    // a trained model, so tuning it can move the loss.
    tch::no_grad(|| {
        for (name, v) in vs.variables() {
            if name.contains("attn.c_") && name.ends_with("weight") {
                let _ = v.shallow_clone().f_mul_scalar_(25.0);
            }
        }
    });
    (vs, m)
}

fn segment(rng: &mut Rng, b: usize, t: usize) -> SegmentBatch {
    let mut u = |n: usize, s: f32| (0..n).map(|_| s * (rng.random::<f32>() * 2.0 - 1.0)).collect();
    SegmentBatch {
        batch: b,
        steps: t,
        state_dim: DS,
        act_dim: DA,
        states: u(b * t * DS, 1.0),
        actions: u(b * t * DA, 0.9),
        returns_to_go: u(b * t, 1.0),
        timesteps: (0..b).flat_map(|_| 0..t as i64).collect(),
        mask: vec![1.0; b * t],
    }
}

/// A fixed demonstration set (every draw returns it) and a starting prompt.
fn fixture() -> (Segments, SegmentBatch) {
    let mut rng = Rng::seed_from_u64(3);
    let demos = segment(&mut rng, 8, K);
    let prompt = segment(&mut rng, 1, LP);
    (segs(&demos), prompt)
}

fn segs(b: &SegmentBatch) -> Segments {
    Segments::from_host(
        b.batch,
        b.steps,
        DS,
        DA,
        &b.states,
        &b.actions,
        &b.returns_to_go,
        &b.timesteps,
        &b.mask,
        Device::Cpu,
    )
}

fn same(s: &Segments) -> Segments {
    Segments {
        states: s.states.shallow_clone(),
        actions: s.actions.shallow_clone(),
        returns_to_go: s.returns_to_go.shallow_clone(),
        timesteps: s.timesteps.shallow_clone(),
        mask: s.mask.shallow_clone(),
    }
}

fn loss(m: &PromptDt, demos: &Segments, prompt: &SegmentBatch) -> f64 {
    let p = prompt_batch(&[prompt], Device::Cpu);
    tch::no_grad(|| demo_loss(m, demos, &m.prompt_tokens(&p), None).double_value(&[]))
}

fn config(kind: AdaptKind, steps: usize, lr: f64) -> AdaptConfig {
    AdaptConfig { kind, steps, batch: 8, lr, ..AdaptConfig::default() }
}

#[test]
fn soft_prompt_moves_the_demonstrations_loss_down() {
    let (_vs, m) = model();
    let (demos, prompt) = fixture();
    let before = loss(&m, &demos, &prompt);
    let mut source = |_: usize, _: &mut Rng| same(&demos);
    let mut rng = Rng::seed_from_u64(1);
    let p = prompt_batch(&[&prompt], Device::Cpu);
    let weights_before = to_vec(&m.prompt_tokens(&p).tokens.detach());
    let cfg = config(AdaptKind::SoftPrompt, 60, 0.1);
    let tuned = adapt::soft_prompt(&m, &p, &cfg, &mut source, &mut rng).unwrap();
    let after = tch::no_grad(|| demo_loss(&m, &demos, &tuned, None).double_value(&[]));
    eprintln!("soft prompt: loss {before} -> {after}");
    assert!(after < 0.9 * before, "soft prompt: loss {before} -> {after}");
    // The backbone is frozen: the same prompt embeds as before.
    assert_eq!(to_vec(&m.prompt_tokens(&p).tokens.detach()), weights_before);
}

#[test]
fn lora_at_step_zero_is_the_frozen_model_and_training_moves_the_loss_down() {
    let (_vs, m) = model();
    let (demos, prompt) = fixture();
    let p = prompt_batch(&[&prompt], Device::Cpu);
    let mut rng = Rng::seed_from_u64(2);
    let mut lcfg = AdaptConfig::default().lora;
    lcfg.c_proj = true;
    let fresh = adapt::new_adapters(&m, &lcfg, &mut rng);
    tch::no_grad(|| {
        // Full forward: prompt repeated per row, as the loss feeds it.
        let rows = prompt_batch(&[&prompt; 8], Device::Cpu);
        let frozen = m.forward(&demos, Sequence::eval(Some(&rows)).all_steps());
        let tokens = m.prompt_tokens(&rows);
        let adapted = m.forward(
            &demos,
            Sequence {
                prompt: Some(Prompt::Tokens(&tokens)),
                lora: Some(&fresh),
                last_block: Some(LastBlock::AllTokens),
                ..Sequence::eval(None)
            }
            .all_steps(),
        );
        assert_eq!(to_vec(&frozen), to_vec(&adapted));
        // Cached acting: prefix and last-step action.
        let one = m.prompt_tokens(&p);
        let index = tch::Tensor::from_slice(&[0i64; 8]);
        let plain =
            m.forward(&demos, Act { prompt: Some(&m.prefix(&p, None).select(&index)), lora: None });
        let with = m.forward(
            &demos,
            Act { prompt: Some(&m.prefix(&one, Some(&fresh)).select(&index)), lora: Some(&fresh) },
        );
        assert_eq!(to_vec(&plain), to_vec(&with));
    });
    let before = loss(&m, &demos, &prompt);
    let mut source = |_: usize, _: &mut Rng| same(&demos);
    let cfg = config(AdaptKind::Lora, 60, 1e-2);
    let a = adapt::lora(&m, &p, &cfg, &mut source, &mut rng).unwrap();
    let tokens = tch::no_grad(|| m.prompt_tokens(&p));
    let after = tch::no_grad(|| demo_loss(&m, &demos, &tokens, Some(&a)).double_value(&[]));
    eprintln!("lora: loss {before} -> {after}");
    assert!(after < 0.9 * before, "lora: loss {before} -> {after}");
    // c_attn only (the default): A [16, 4] and B [4, 48] per block.
    assert_eq!(a.numel(), 2 * (16 * 4 + 4 * 48));
}

/// Every variable of `vs`, by name, as host values.
fn weights_of(vs: &VarStore) -> std::collections::BTreeMap<String, Vec<f32>> {
    vs.variables().into_iter().map(|(n, t)| (n, to_vec(&t.detach()))).collect()
}

/// Writes `saved` (from [`weights_of`]) back into `vs`.
fn restore(vs: &VarStore, saved: &std::collections::BTreeMap<String, Vec<f32>>) {
    tch::no_grad(|| {
        for (n, v) in vs.variables() {
            let t = tch::Tensor::from_slice(&saved[&n]).reshape(v.size());
            v.shallow_clone().copy_(&t);
        }
    });
}

#[test]
fn full_fine_tuning_changes_the_weights_reproducibly_and_zero_steps_changes_nothing() {
    let (vs, m) = model();
    let (demos, prompt) = fixture();
    let p = prompt_batch(&[&prompt], Device::Cpu);
    let trainable = vs.trainable_variables();
    let before = weights_of(&vs);
    let rows = prompt_batch(&[&prompt; 8], Device::Cpu);
    let out = |m: &PromptDt| {
        tch::no_grad(|| to_vec(&m.forward(&demos, Sequence::eval(Some(&rows)).all_steps())))
    };
    let frozen = out(&m);

    // 0 steps: every weight, and so every output, as trained (the reference rule's policy).
    let mut source = |_: usize, _: &mut Rng| same(&demos);
    let zero = config(AdaptKind::Full, 0, 1e-3);
    adapt::full(&m, &trainable, &p, &zero, &mut source, &mut Rng::seed_from_u64(4)).unwrap();
    assert_eq!(weights_of(&vs), before);
    assert_eq!(out(&m), frozen);

    // Tuned: the loss goes down and the weights move, the prompt embeddings and the trunk alike;
    // the heads the loss never reaches (kept for the reference's weights) stay.
    let loss_before = loss(&m, &demos, &prompt);
    let cfg = config(AdaptKind::Full, 30, 1e-3);
    let tune = |seed: u64| {
        let mut source = |_: usize, _: &mut Rng| same(&demos);
        adapt::full(&m, &trainable, &p, &cfg, &mut source, &mut Rng::seed_from_u64(seed)).unwrap();
        weights_of(&vs)
    };
    let tuned = tune(4);
    let loss_after = loss(&m, &demos, &prompt);
    eprintln!("full: loss {loss_before} -> {loss_after}");
    assert!(loss_after < 0.9 * loss_before, "full: loss {loss_before} -> {loss_after}");
    let moved: Vec<&String> = tuned.keys().filter(|n| tuned[*n] != before[*n]).collect();
    for part in
        ["prompt_embed_state", "embed_state", "transformer.h.0.attn.c_attn", "predict_action"]
    {
        assert!(moved.iter().any(|n| n.starts_with(part)), "{part} did not move: {moved:?}");
    }
    // What stays is only what the loss never reaches.
    let unused = ["predict_state.", "predict_return.", "transformer.wte."];
    for n in before.keys().filter(|n| !moved.contains(n)) {
        assert!(unused.iter().any(|u| n.starts_with(u)), "{n} did not move");
    }

    // Reproducible: from the same weights and seed, the same weights bit for bit; restored, the
    // model is the one it was.
    restore(&vs, &before);
    assert_eq!(out(&m), frozen);
    assert_eq!(tune(4), tuned);
    restore(&vs, &before);
    assert_eq!(weights_of(&vs), before);
}

#[test]
fn ptdt_moves_the_demonstrations_loss_down() {
    let (_vs, m) = model();
    let (demos, prompt) = fixture();
    let before = loss(&m, &demos, &prompt);
    let mut source = |_: usize, _: &mut Rng| same(&demos);
    let mut score = ActionLossScore { model: &m, batch: 8, demos: &mut source };
    let mut rng = Rng::seed_from_u64(5);
    let mut cfg = config(AdaptKind::Ptdt, 30, 1e-3);
    cfg.ptdt.sigma = 0.5;
    cfg.ptdt.step = 0.5;
    let tuned = adapt::ptdt(&prompt, &cfg, &mut score, &mut rng).unwrap();
    let after = loss(&m, &demos, &tuned);
    eprintln!("ptdt: loss {before} -> {after}");
    assert!(after < 0.97 * before, "ptdt: loss {before} -> {after}");
    assert_eq!(tuned.timesteps, prompt.timesteps);
    assert_eq!(tuned.mask, prompt.mask);
}

#[test]
fn the_ranking_direction_points_to_the_better_candidate() {
    // Two candidates: the better one's perturbation minus the worse one's.
    let us = vec![vec![1.0, 0.0], vec![0.0, 1.0]];
    assert_eq!(rank_direction(&us, &[2.0, 1.0]), vec![1.0, -1.0]);
    assert_eq!(rank_direction(&us, &[1.0, 2.0]), vec![-1.0, 1.0]);
    // Only the ranking counts, not the scale.
    assert_eq!(rank_direction(&us, &[1e9, -3.0]), vec![1.0, -1.0]);
    // Ties teach nothing.
    assert_eq!(rank_direction(&us, &[1.0, 1.0]), vec![0.0, 0.0]);
    // Three candidates: the direction leans towards the best and away from the worst.
    let us3 = vec![vec![1.0, 0.0, 0.0], vec![0.0, 1.0, 0.0], vec![0.0, 0.0, 1.0]];
    let g = rank_direction(&us3, &[0.5, 3.0, -1.0]);
    assert!(g[1] > g[0] && g[0] > g[2], "{g:?}");
}

/// A constructed score: minus the squared distance of the prompt's states to a target.
struct Target(Vec<f32>);

impl PromptScore for Target {
    fn scores(&mut self, c: &[SegmentBatch], _: &mut Rng) -> Result<Vec<f64>, EvalError> {
        Ok(c.iter().map(|p| -dist(&p.states, &self.0)).collect())
    }
}

fn dist(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| f64::from(x - y).powi(2)).sum()
}

#[test]
fn ptdt_moves_the_prompt_towards_the_better_candidates() {
    let mut rng = Rng::seed_from_u64(9);
    let prompt = segment(&mut rng, 1, LP);
    let target: Vec<f32> = prompt.states.iter().map(|x| x + 0.5).collect();
    let before = dist(&prompt.states, &target);
    let mut cfg = config(AdaptKind::Ptdt, 50, 1e-3);
    cfg.ptdt.sigma = 0.05;
    cfg.ptdt.step = 0.05;
    let tuned = adapt::ptdt(&prompt, &cfg, &mut Target(target.clone()), &mut rng).unwrap();
    let after = dist(&tuned.states, &target);
    assert!(after < 0.5 * before, "distance {before} -> {after}");
}

#[test]
fn bad_settings_are_refused_with_their_value() {
    let e = "tail".parse::<AdaptKind>().unwrap_err().to_string();
    assert!(e.contains("`tail`") && e.contains("soft-prompt, ptdt, lora, full"), "{e}");
    let mut c = config(AdaptKind::Lora, 10, 1e-3);
    c.lora.rank = 0;
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("eval.adapt.lora.rank = 0"), "{e}");
    let mut c = config(AdaptKind::Ptdt, 10, 1e-3);
    c.ptdt.candidates = 1;
    assert!(c.validate().unwrap_err().to_string().contains("eval.adapt.ptdt.candidates = 1"));
    let c = config(AdaptKind::SoftPrompt, 10, f64::NAN);
    assert!(c.validate().unwrap_err().to_string().contains("eval.adapt.lr = NaN"));
}
