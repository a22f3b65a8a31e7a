//! The pack tests' fixture (`pack_batched.rs`, `pack_flat.rs`): a small model, three runs that
//! differ in seed, prompt length and loss, their batches as deterministic random tensors of the
//! sampler's shapes, and comparisons of tensors and slot states.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)] // each including test uses its part

use pdt_base::seed::derive_seed;
use pdt_model::{PromptDt, PromptDtConfig, Segments};
use pdt_pack::{BatchedEngine, PackEngine, PackLayout, SlotSpec, SlotStep};
use pdt_rundir::config::AdamWConfig;
use pdt_rundir::config::LossOn;
use pdt_train::optim::SlotState;
use pdt_train::optim::{AdamW, Optimizer};
use pdt_train::step::{DeviceBatch, PendingStats};
use tch::{nn::VarStore, Device, Kind, Tensor};

// libtorch's generator is global: the tests of this binary take turns.
pub use pdt_testkit::process::LIBTORCH as RNG;

pub fn lock() -> pdt_testkit::process::Alone {
    RNG.lock().unwrap_or_else(|e| e.into_inner())
}

/// `crate::streams`: model initialisation and dropout streams of a run seed.
pub const STREAM_INIT: u64 = 1;
pub const STREAM_DROPOUT: u64 = 3;

pub const B: usize = 6;
pub const K: usize = 5;
pub const P: usize = 4;

pub fn cfg() -> PromptDtConfig {
    PromptDtConfig {
        hidden_size: 32,
        n_layer: 2,
        n_head: 2,
        n_inner: 64,
        max_ep_len: 60,
        n_positions: 3 * (P + K) + 6,
        ..PromptDtConfig::reference(5, 3)
    }
}

pub fn layout() -> PackLayout {
    PackLayout { batch_size: B, history_len: K, prompt_len: P }
}

pub fn optim() -> AdamWConfig {
    AdamWConfig { learning_rate: 1e-3, warmup_steps: 10, ..AdamWConfig::default() }
}

/// Run i of the pack: seed, prompt length (0: no prompt), loss.
pub struct Run {
    pub seed: u64,
    pub prompt: usize,
    pub loss_on: LossOn,
}

/// Three runs: a Prompt-DT run, an MT-ORL-like run without prompt, and a run with a shorter
/// prompt whose loss also reads its prompt steps.
pub const RUNS: [Run; 3] = [
    Run { seed: 11, prompt: P, loss_on: LossOn::History },
    Run { seed: 12, prompt: 0, loss_on: LossOn::History },
    Run { seed: 13, prompt: 2, loss_on: LossOn::PromptAndHistory },
];

pub fn specs() -> Vec<SlotSpec> {
    RUNS.iter()
        .map(|r| SlotSpec {
            model: cfg(),
            uses_prompt: r.prompt > 0,
            loss_on: r.loss_on,
            optim: optim(),
            last_block: pdt_rundir::config::LastBlockChoice::Auto,
            seed: r.seed,
        })
        .collect()
}

/// Host values of a small deterministic generator (SplitMix64), uniform in [0, 1).
pub fn uniform(seed: u64, n: usize) -> Vec<f32> {
    (0..n as u64).map(|i| (derive_seed(seed, 99, i) >> 40) as f32 / (1u64 << 24) as f32).collect()
}

/// Segments of `t` steps as the sampler makes them: sample `b` has `b % 3` left-padded steps
/// (zeros, mask 0), returns-to-go and states of a few units, actions in (-1, 1).
pub fn segments(seed: u64, t: usize) -> Segments {
    let c = cfg();
    let (ds, da) = (c.state_dim, c.act_dim);
    let mut states = uniform(seed, B * t * ds).iter().map(|u| 4.0 * u - 2.0).collect::<Vec<_>>();
    let mut actions =
        uniform(seed + 1, B * t * da).iter().map(|u| 1.8 * u - 0.9).collect::<Vec<_>>();
    let mut rtg = uniform(seed + 2, B * t).iter().map(|u| 3.0 * u).collect::<Vec<_>>();
    let start = uniform(seed + 3, B);
    let mut timesteps = vec![0i64; B * t];
    let mut mask = vec![1f32; B * t];
    for (b, &s0) in start.iter().enumerate() {
        let pad = (b % 3).min(t - 1);
        let t0 = (s0 * (c.max_ep_len - t) as f32) as i64;
        for s in 0..t {
            let i = b * t + s;
            if s < pad {
                mask[i] = 0.0;
                rtg[i] = 0.0;
                states[i * ds..(i + 1) * ds].fill(0.0);
                actions[i * da..(i + 1) * da].fill(0.0);
            } else {
                timesteps[i] = t0 + s as i64;
            }
        }
    }
    Segments::from_host(B, t, ds, da, &states, &actions, &rtg, &timesteps, &mask, Device::Cpu)
}

/// Run `run`'s batch of gradient step `step` (the same each time it is asked for).
pub fn batch(run: usize, step: u64) -> DeviceBatch {
    let seed = 1000 * run as u64 + 7 * step;
    let r = &RUNS[run];
    DeviceBatch {
        history: segments(seed, K),
        prompt: (r.prompt > 0).then(|| segments(seed + 500, r.prompt)),
    }
}

/// A solo model initialised as run `run`'s solo learner initialises it.
pub fn solo(run: usize) -> (VarStore, PromptDt) {
    tch::manual_seed(derive_seed(RUNS[run].seed, STREAM_INIT, 0) as i64);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &cfg());
    (vs, model)
}

pub fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size());
    (a.to_kind(Kind::Double) - b.to_kind(Kind::Double)).abs().max().double_value(&[])
}

/// Bit for bit (NaN equal to the same NaN): float tensors compared as their bits.
pub fn bit_equal(a: &Tensor, b: &Tensor) -> bool {
    a.size() == b.size()
        && a.kind() == b.kind()
        && a.view_dtype(Kind::Int).eq_tensor(&b.view_dtype(Kind::Int)).all().int64_value(&[]) == 1
}

/// The per-tensor optimiser of a solo run (the bitwise-PyTorch one the pack is compared with).
pub fn adam(opt: &Optimizer) -> &AdamW {
    match opt {
        Optimizer::PerTensor(a) => a,
        Optimizer::Flat(_) => panic!("the solo runs of these tests use the per-tensor AdamW"),
    }
}

pub fn engine() -> BatchedEngine {
    BatchedEngine::new(specs(), layout(), Device::Cpu).unwrap()
}

pub fn steps_of(step: u64, active: [bool; 3]) -> Vec<Option<SlotStep>> {
    (0..3).map(|i| active[i].then(|| SlotStep { step, batch: batch(i, step) })).collect()
}

pub fn assert_same_state(what: &str, a: &SlotState, b: &SlotState) {
    assert_eq!(a.weights.len(), b.weights.len(), "{what}");
    for ((na, ta), (nb, tb)) in a.weights.iter().zip(&b.weights) {
        assert_eq!(na, nb, "{what}");
        assert!(bit_equal(ta, tb), "{what}: weight {na} differs");
    }
    assert_eq!(
        a.moments.keys().collect::<Vec<_>>(),
        b.moments.keys().collect::<Vec<_>>(),
        "{what}"
    );
    for (name, ma) in &a.moments {
        let mb = &b.moments[name];
        assert_eq!(ma.step, mb.step, "{what}: step of {name}");
        assert!(bit_equal(&ma.exp_avg, &mb.exp_avg), "{what}: exp_avg of {name}");
        assert!(bit_equal(&ma.exp_avg_sq, &mb.exp_avg_sq), "{what}: exp_avg_sq of {name}");
    }
}

/// A run's stats and state do not depend on which of its pack-mates are stepped, nor on a
/// pack-mate that diverged (NaN weights), and a run not stepped is left as it was; for packs made
/// by `make`.
pub fn assert_runs_independent(make: &dyn Fn() -> BatchedEngine) {
    let _g = lock();
    const STEPS: u64 = 6;
    let mut all = make();
    let mut some = make();
    let mut poisoned = make();
    // Run 2 of `poisoned` diverged: NaN weights. Its NaN must not reach runs 0 and 1.
    let mut state = poisoned.export(2).unwrap();
    for (name, t) in &mut state.weights {
        if name.starts_with("transformer.h.0.attn.c_attn.weight") {
            *t = t.fill(f64::NAN);
        }
    }
    poisoned.import(2, state).unwrap();
    let before = some.export(2).unwrap();
    for step in 0..STEPS {
        let a = PendingStats::read_slots(all.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        // Run 1 every other step, run 2 never.
        let s = PendingStats::read_slots(
            some.step(steps_of(step, [true, step % 2 == 0, false])).unwrap(),
        )
        .unwrap();
        let p =
            PendingStats::read_slots(poisoned.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        assert_eq!(a[0], s[0], "step {step}: run 0's stats depend on which runs are stepped");
        assert_eq!(a[0], p[0], "step {step}: run 0's stats depend on a diverged pack-mate");
        assert_eq!(a[1], p[1], "step {step}: run 1's stats depend on a diverged pack-mate");
        assert!(s[2].is_none());
        let p2 = p[2].unwrap();
        assert!(p2.loss.is_nan(), "the diverged run reports its NaN loss, got {}", p2.loss);
    }
    assert_same_state(
        "run 0, pack-mates stepped or not",
        &some.export(0).unwrap(),
        &all.export(0).unwrap(),
    );
    assert_same_state(
        "run 0, pack-mate diverged",
        &poisoned.export(0).unwrap(),
        &all.export(0).unwrap(),
    );
    assert_same_state(
        "run 1, pack-mate diverged",
        &poisoned.export(1).unwrap(),
        &all.export(1).unwrap(),
    );
    assert_same_state("run 2, never stepped", &some.export(2).unwrap(), &before);
    // No step at all leaves everything as it was.
    let out = PendingStats::read_slots(some.step((0..3).map(|_| None).collect()).unwrap()).unwrap();
    assert!(out.iter().all(Option::is_none));
    assert_same_state(
        "run 0 after an empty step",
        &some.export(0).unwrap(),
        &all.export(0).unwrap(),
    );
}
