//! The solo pack engine (each run's solo step, one run after another: the batched engine's
//! oracle) against the solo step: every step's statistics and every weight and AdamW moment bit
//! for bit those of each run's own `train_step` loop, a run given no input left untouched; and
//! dropout masks drawn beforehand equal to the forward's own (`pdt_model::dropout`, which the
//! batched engine's CPU masks rest on).
//!
//! Batches are random tensors of the sampler's shapes on a small two-head model: a Prompt-DT run,
//! an MT-ORL-like run without prompt, and a run whose loss also reads its (shorter) prompt.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_base::seed::derive_seed;
use pdt_model::dropout::{Dropout, DropoutMasks};
use pdt_model::prompt_dt::Sequence;
use pdt_model::{PromptDt, PromptDtConfig, Segments};
use pdt_pack::{PackEngine, SlotSpec, SlotStep, SoloEngine};
use pdt_rundir::config::AdamWConfig;
use pdt_rundir::config::LossOn;
use pdt_train::optim::Optimizer;
use pdt_train::optim::SlotState;
use pdt_train::step::{train_step, DeviceBatch, PendingStats, StepStats};
use tch::{nn::VarStore, Device, Kind, Tensor};

// libtorch's generator is global: the tests of this binary take turns.
use pdt_testkit::process::LIBTORCH as RNG;

fn lock() -> pdt_testkit::process::Alone {
    RNG.lock().unwrap_or_else(|e| e.into_inner())
}

/// `crate::streams`: the model initialisation and dropout streams of a run seed.
const STREAM_INIT: u64 = 1;
const STREAM_DROPOUT: u64 = 3;

const B: usize = 6;
const K: usize = 5;
const P: usize = 4;

fn cfg() -> PromptDtConfig {
    PromptDtConfig {
        hidden_size: 32,
        n_layer: 2,
        n_head: 2,
        n_inner: 64,
        max_ep_len: 60,
        n_positions: 3 * (P + K),
        ..PromptDtConfig::reference(5, 3)
    }
}

/// Run i of the pack: seed, prompt length (0: no prompt), loss.
const RUNS: [(u64, usize, LossOn); 3] =
    [(11, P, LossOn::History), (12, 0, LossOn::History), (13, 2, LossOn::PromptAndHistory)];

fn specs() -> Vec<SlotSpec> {
    RUNS.iter()
        .map(|&(seed, prompt, loss_on)| SlotSpec {
            model: cfg(),
            uses_prompt: prompt > 0,
            loss_on,
            optim: AdamWConfig { learning_rate: 1e-3, warmup_steps: 10, ..AdamWConfig::default() },
            last_block: pdt_rundir::config::LastBlockChoice::Auto,
            seed,
        })
        .collect()
}

/// Host values uniform in [0, 1) from the project's SplitMix64.
fn uniform(seed: u64, n: usize) -> Vec<f32> {
    (0..n as u64).map(|i| (derive_seed(seed, 99, i) >> 40) as f32 / (1u64 << 24) as f32).collect()
}

/// `t` steps per sample, sample `b` left-padded by `b % 3` masked steps.
fn segments(seed: u64, t: usize) -> Segments {
    let c = cfg();
    let (ds, da) = (c.state_dim, c.act_dim);
    let states: Vec<f32> = uniform(seed, B * t * ds).iter().map(|u| 4.0 * u - 2.0).collect();
    let actions: Vec<f32> = uniform(seed + 1, B * t * da).iter().map(|u| 1.8 * u - 0.9).collect();
    let rtg: Vec<f32> = uniform(seed + 2, B * t).iter().map(|u| 3.0 * u).collect();
    let mut timesteps = vec![0i64; B * t];
    let mut mask = vec![1f32; B * t];
    for b in 0..B {
        for s in 0..t {
            if s < (b % 3).min(t - 1) {
                mask[b * t + s] = 0.0;
            } else {
                timesteps[b * t + s] = (3 * b + s) as i64;
            }
        }
    }
    Segments::from_host(B, t, ds, da, &states, &actions, &rtg, &timesteps, &mask, Device::Cpu)
}

/// Run `run`'s batch of gradient step `step` (the same each time it is asked for).
fn batch(run: usize, step: u64) -> DeviceBatch {
    let seed = 1000 * run as u64 + 7 * step;
    let prompt = RUNS[run].1;
    DeviceBatch {
        history: segments(seed, K),
        prompt: (prompt > 0).then(|| segments(seed + 500, prompt)),
    }
}

/// Run `run` as a solo learner holds it: its model initialised from its seed, its optimiser.
struct Solo {
    vs: VarStore,
    model: PromptDt,
    opt: Optimizer,
}

fn solo(run: usize) -> Solo {
    tch::manual_seed(derive_seed(RUNS[run].0, STREAM_INIT, 0) as i64);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &cfg());
    let opt = Optimizer::new(&vs, &cfg().parameter_names(), specs()[run].optim.clone());
    Solo { vs, model, opt }
}

/// Bit for bit (NaN equal to the same NaN): float tensors compared as their bits.
fn bit_equal(a: &Tensor, b: &Tensor) -> bool {
    a.size() == b.size()
        && a.kind() == b.kind()
        && a.view_dtype(Kind::Int).eq_tensor(&b.view_dtype(Kind::Int)).all().int64_value(&[]) == 1
}

fn assert_same_state(what: &str, a: &SlotState, b: &SlotState) {
    assert_eq!(a.weights.len(), b.weights.len(), "{what}");
    for ((na, ta), (nb, tb)) in a.weights.iter().zip(&b.weights) {
        assert_eq!(na, nb, "{what}");
        assert!(bit_equal(ta, tb), "{what}: weight {na} differs");
    }
    assert_eq!(a.moments.len(), b.moments.len(), "{what}");
    for (name, ma) in &a.moments {
        let mb = &b.moments[name];
        assert_eq!(ma.step, mb.step, "{what}: step of {name}");
        assert!(bit_equal(&ma.exp_avg, &mb.exp_avg), "{what}: exp_avg of {name}");
        assert!(bit_equal(&ma.exp_avg_sq, &mb.exp_avg_sq), "{what}: exp_avg_sq of {name}");
    }
}

/// Which runs step at gradient step `s`: all, but run 1 sits out steps 3 and 4 and run 2 step 7
/// (their step indices go on from where they stopped).
fn active(s: u64) -> [bool; 3] {
    [true, !(3..5).contains(&s), s != 7]
}

#[test]
fn runs_stepped_in_turn_are_their_solo_steps_bit_for_bit() {
    // Against solo steps with the same libtorch thread count (results depend on it).
    let _g = lock();
    for threads in [1, 2] {
        tch::set_num_threads(threads);
        stepped_as_alone(threads);
    }
}

fn stepped_as_alone(threads: i32) {
    let mut engine = SoloEngine::new(specs(), Device::Cpu);
    let mut alone: Vec<Solo> = (0..3).map(solo).collect();
    for (i, s) in alone.iter().enumerate() {
        engine.import(i, SlotState::copy_of(&s.vs, &s.opt)).unwrap();
    }
    let mut next = [0u64; 3];
    for s in 0..12 {
        let on = active(s);
        if s == 9 {
            // Run 2 goes on at another step (as a run resumed from elsewhere).
            next[2] += 5;
        }
        let before: Vec<SlotState> = (0..3).map(|i| engine.export(i).unwrap()).collect();
        let steps: Vec<Option<SlotStep>> = (0..3)
            .map(|i| on[i].then(|| SlotStep { step: next[i], batch: batch(i, next[i]) }))
            .collect();
        let got: Vec<Option<StepStats>> =
            PendingStats::read_slots(engine.step(steps).unwrap()).unwrap();
        for i in 0..3 {
            if !on[i] {
                assert!(got[i].is_none(), "step {s}: run {i} got a result without an input");
                assert_same_state(
                    &format!("step {s}: run {i}, given no input"),
                    &engine.export(i).unwrap(),
                    &before[i],
                );
                continue;
            }
            let a = &mut alone[i];
            tch::manual_seed(derive_seed(RUNS[i].0, STREAM_DROPOUT, next[i]) as i64);
            let want: StepStats =
                train_step(&a.model, &mut a.opt, &batch(i, next[i]), RUNS[i].2, next[i]).unwrap();
            let st = got[i].unwrap();
            let at = format!("{threads} threads, step {s}: run {i}");
            assert_eq!(st.loss.to_bits(), want.loss.to_bits(), "{at}: loss");
            assert_eq!(st.grad_norm.to_bits(), want.grad_norm.to_bits(), "{at}: gradient norm");
            assert_eq!(st.lr, want.lr, "{at}");
            next[i] += 1;
        }
    }
    for (i, a) in alone.iter().enumerate() {
        assert_same_state(
            &format!("{threads} threads: run {i} after 12 steps"),
            &engine.export(i).unwrap(),
            &SlotState::copy_of(&a.vs, &a.opt),
        );
    }
    // A batch that does not fit its run (a prompt for the run without one) is refused by slot.
    let mut bad: Vec<Option<SlotStep>> = (0..3).map(|_| None).collect();
    bad[1] = Some(SlotStep { step: 0, batch: batch(0, 0) });
    let e = engine.step(bad).unwrap_err().to_string();
    assert!(e.contains("slot 1"), "{e}");
}

#[test]
fn masks_drawn_beforehand_are_the_masks_the_forward_draws() {
    let _g = lock();
    let s = solo(0);
    let b = batch(0, 0);
    let (h, p) = (&b.history, b.prompt.as_ref());
    tch::manual_seed(5);
    let drawn = s.model.forward(h, Sequence::train(p));
    let len = PromptDt::token_count(h, p);
    let draw = || DropoutMasks::draw(&s.model.cfg, h.batch_size(), len, h.states.device());
    tch::manual_seed(5);
    let masks = draw();
    let given = s.model.forward(h, Sequence::new(p, Dropout::Given(&masks)));
    assert!(bit_equal(&drawn, &given));
    // Dropout is on: another seed's masks give other predictions.
    tch::manual_seed(6);
    let other = draw();
    assert!(!bit_equal(&drawn, &s.model.forward(h, Sequence::new(p, Dropout::Given(&other)))));
}
