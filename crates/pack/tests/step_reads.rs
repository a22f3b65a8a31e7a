//! A training step leaves its loss and gradient norm on the device: no step reads a value back
//! (on a GPU a read waits for the step's kernels, and the device idles while the host prepares the
//! next step). The run loops read an iteration's statistics once, after its last step
//! (`PendingStats::read_all`), and get the values reading each step at once gives, bit for bit.
//! In its own binary, one test: libtorch's profiler sees every thread's operators and is started
//! from one thread. (So not a module of `tests/it`, whose other tests would run operators beside
//! it: a second integration-test binary of this crate, kept apart on purpose.)
#![allow(clippy::unwrap_used)] // test: a failed unwrap is a failed test

#[path = "it/support/pack_fixture.rs"]
mod fixture;

use fixture::*;
use pdt_model::dropout::Dropout;
use pdt_pack::PackEngine;
use pdt_rundir::config::{AdamWConfig, FlatOptim};
use pdt_torch::profiler;
use pdt_train::optim::Optimizer;
use pdt_train::step::{train_step, train_step_with, PendingStats, StepStats};

/// The operators that read a tensor's value to the host (`double_value`, `.item()`).
const READS: [&str; 2] = ["aten::item", "aten::_local_scalar_dense"];

fn reads(events: &[profiler::Event]) -> Vec<String> {
    events.iter().filter(|e| READS.contains(&e.name.as_str())).map(|e| e.name.clone()).collect()
}

#[test]
fn steps_read_nothing_back_and_read_later_give_the_values_of_reading_at_once() {
    let _rng = lock();
    solo_steps();
    batched_pack_steps();
}

/// A solo step, with either optimiser.
fn solo_steps() {
    let steps = 4u64;
    for flat in [FlatOptim::Off, FlatOptim::On] {
        let names = cfg().parameter_names();
        let ocfg = AdamWConfig { flat, ..optim() };
        // The same run twice: its statistics read at once (`train_step`), and left pending over
        // its steps, then read together.
        let (vs_a, model_a) = solo(0);
        let mut opt_a = Optimizer::new(&vs_a, &names, ocfg.clone());
        let want: Vec<StepStats> = (0..steps)
            .map(|s| {
                tch::manual_seed(s as i64);
                train_step(&model_a, &mut opt_a, &batch(0, s), RUNS[0].loss_on, s).unwrap()
            })
            .collect();
        let (vs_b, model_b) = solo(0);
        let mut opt_b = Optimizer::new(&vs_b, &names, ocfg);
        let mut pending = Vec::new();
        for s in 0..steps {
            let b = batch(0, s);
            tch::manual_seed(s as i64);
            let p = profiler::start(false).unwrap();
            let st = train_step_with(&model_b, &mut opt_b, &b, RUNS[0].loss_on, s, Dropout::Draw);
            let events = p.stop().unwrap();
            assert!(events.len() > 100, "{flat:?}: the profiler saw the step ({})", events.len());
            assert_eq!(reads(&events), Vec::<String>::new(), "{flat:?}, step {s}");
            pending.push(st);
        }
        let got = PendingStats::read_all(pending).unwrap();
        assert_eq!(got, want, "{flat:?}");
        assert!(got.iter().all(|s| s.loss > 0.0 && s.grad_norm > 0.0), "{got:?}");
    }
}

/// A batched pack's step; each run reads its own statistics.
fn batched_pack_steps() {
    let mut e = engine();
    let mut twin = engine();
    for s in 0..3u64 {
        // Run 1 sits out the second step.
        let active = [true, s != 1, true];
        let p = profiler::start(false).unwrap();
        let pending = e.step(steps_of(s, active)).unwrap();
        let events = p.stop().unwrap();
        assert!(events.len() > 100, "the profiler saw the step ({})", events.len());
        assert_eq!(reads(&events), Vec::<String>::new(), "step {s}");
        let got = PendingStats::read_slots(pending).unwrap();
        // The twin pack's statistics read one run at a time, in reverse order: each run's own.
        let mut twin_out = twin.step(steps_of(s, active)).unwrap();
        for run in (0..3).rev() {
            let one = twin_out[run].take().map(|p| p.read().unwrap());
            assert_eq!(got[run], one, "step {s}, run {run}");
            assert_eq!(got[run].is_some(), active[run], "step {s}, run {run}");
        }
    }
}
