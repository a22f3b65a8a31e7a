//! The batched engine's flat mode (the pack's optimiser on one run-major buffer, the
//! CUDA default) and its per-run dropout draw (`MaskDraw::PerRun`, the CUDA default), on the CPU:
//! the flat pack against the per-tensor pack with the same masks, the per-tensor fallback for
//! uneven step counts, and the independence of a run from its pack-mates in either draw.
#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: a failed unwrap is a failed test

use crate::fixture;

use fixture::*;
use pdt_pack::model::MaskDraw;
use pdt_pack::{BatchedEngine, PackEngine, SlotSpec};
use pdt_rundir::config::FlatOptim;
use pdt_train::optim::SlotState;
use pdt_train::step::PendingStats;
use tch::{Device, Tensor};

fn flat_specs() -> Vec<SlotSpec> {
    let mut specs = specs();
    for s in &mut specs {
        s.optim.flat = FlatOptim::On;
    }
    specs
}

fn flat_engine(draw: MaskDraw) -> BatchedEngine {
    let mut e = BatchedEngine::new(flat_specs(), layout(), Device::Cpu).unwrap();
    assert!(e.is_flat(), "optim.flat = on gives the flat optimiser on the CPU too");
    e.set_mask_draw(draw);
    e
}

fn copy_state(s: &SlotState) -> SlotState {
    SlotState {
        weights: s.weights.iter().map(|(n, t)| (n.clone(), t.copy())).collect(),
        moments: s
            .moments
            .iter()
            .map(|(n, m)| {
                let m = pdt_train::optim::ParamState {
                    step: m.step,
                    exp_avg: m.exp_avg.copy(),
                    exp_avg_sq: m.exp_avg_sq.copy(),
                };
                (n.clone(), m)
            })
            .collect(),
    }
}

fn never_read(run: usize, name: &str) -> bool {
    name.starts_with("transformer.wte")
        || name.starts_with("predict_state")
        || name.starts_with("predict_return")
        || (RUNS[run].prompt == 0 && name.starts_with("prompt_"))
}

#[test]
fn the_flat_pack_trains_as_the_per_tensor_pack() {
    let _g = lock();
    const STEPS: u64 = 50;
    let mut pt = engine();
    assert!(!pt.is_flat(), "optim.flat = auto is per-tensor on the CPU");
    let mut fl = flat_engine(MaskDraw::SoloOrder);
    let init: Vec<SlotState> = (0..3).map(|r| fl.export(r).unwrap()).collect();
    for (run, st) in init.iter().enumerate() {
        assert_same_state("fresh flat pack", st, &pt.export(run).unwrap());
    }
    let (mut loss_d, mut norm_d, mut w_d): (f64, f64, f64) = (0.0, 0.0, 0.0);
    for step in 0..STEPS {
        let a = PendingStats::read_slots(pt.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        let b = PendingStats::read_slots(fl.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        for (a, b) in a.iter().zip(&b) {
            let (a, b) = (a.unwrap(), b.unwrap());
            assert_eq!(a.lr, b.lr, "step {step}: learning rate");
            loss_d = loss_d.max((a.loss - b.loss).abs());
            norm_d = norm_d.max((a.grad_norm - b.grad_norm).abs() / a.grad_norm);
        }
    }
    for (run, first_state) in init.iter().enumerate() {
        let (a, b) = (pt.export(run).unwrap(), fl.export(run).unwrap());
        for ((name, ta), (_, tb)) in a.weights.iter().zip(&b.weights) {
            if never_read(run, name) {
                let first = &first_state.weights.iter().find(|(n, _)| n == name).unwrap().1;
                assert!(bit_equal(tb, first), "run {run}: {name} is never read and must not move");
            }
            w_d = w_d.max(max_diff(ta, tb));
        }
        assert_eq!(
            a.moments.keys().collect::<Vec<_>>(),
            b.moments.keys().collect::<Vec<_>>(),
            "run {run}: the same parameters have moments"
        );
        for (name, m) in &a.moments {
            assert_eq!(b.moments[name].step, m.step, "run {run}: {name} step count");
        }
    }
    eprintln!(
        "flat vs per-tensor pack, {STEPS} steps: max |loss diff| {loss_d:e}, max rel grad-norm \
         diff {norm_d:e}, max |weight diff| {w_d:e}"
    );
    // The clipping norm is one reduction per run instead of the norm of per-tensor norms, so the
    // two differ in the last bits and drift apart slowly through the updates. Measured (AMD EPYC,
    // AVX2, libtorch 2.11, 2 threads): losses 1.2e-7, gradient norms 2.1e-7 relative, final
    // weights 1.3e-6; the bounds are 10-17x those (as the pack-vs-solo test's).
    assert!(loss_d <= 2e-6, "losses differ by {loss_d:e}");
    assert!(norm_d <= 3e-6, "gradient norms differ by {norm_d:e} (relative)");
    assert!(w_d <= 2e-5, "final weights differ by {w_d:e}");
}

/// A state whose parameters are at different step counts (imported from elsewhere) cannot take
/// the flat update (one bias correction per run): the step falls back to the per-tensor loop
/// over the flat buffers' views, and gives the per-tensor pack's bits.
#[test]
fn uneven_step_counts_take_the_per_tensor_loop() {
    let _g = lock();
    let mut pt = engine();
    for step in 0..3 {
        pt.step(steps_of(step, [true; 3])).unwrap();
    }
    let mut state = pt.export(0).unwrap();
    let name = "transformer.h.0.mlp.c_fc.weight";
    state.moments.get_mut(name).unwrap().step = 1;
    let mut fl = flat_engine(MaskDraw::SoloOrder);
    let mut pt2 = engine();
    fl.import(0, copy_state(&state)).unwrap();
    pt2.import(0, state).unwrap();
    for step in 3..5 {
        let a = PendingStats::read_slots(pt2.step(steps_of(step, [true, false, false])).unwrap())
            .unwrap();
        let b = PendingStats::read_slots(fl.step(steps_of(step, [true, false, false])).unwrap())
            .unwrap();
        assert_eq!(a[0], b[0], "step {step}: the fallback is the per-tensor loop, bit for bit");
    }
    let (a, b) = (pt2.export(0).unwrap(), fl.export(0).unwrap());
    assert_same_state("run 0 after the fallback steps", &b, &a);
    assert_eq!(b.moments[name].step, 3, "its own count went on");
    assert_eq!(b.moments["transformer.h.0.attn.c_attn.weight"].step, 5);
}

#[test]
fn a_flat_run_does_not_depend_on_its_pack_mates() {
    assert_runs_independent(&|| flat_engine(MaskDraw::SoloOrder));
}

#[test]
fn a_run_with_per_run_masks_does_not_depend_on_its_pack_mates() {
    assert_runs_independent(&|| flat_engine(MaskDraw::PerRun));
}

/// Per-run masks come from the run's own seed: the same bits in every pack with the same runs; a
/// padded run's differ from the solo order's (drawn at the pack's length), an unpadded run's are
/// the same on the CPU.
#[test]
fn per_run_masks_are_seeded_and_applied() {
    let _g = lock();
    let mut a = flat_engine(MaskDraw::PerRun);
    let mut b = flat_engine(MaskDraw::PerRun);
    let mut solo_order = flat_engine(MaskDraw::SoloOrder);
    for step in 0..3 {
        let x = PendingStats::read_slots(a.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        let y = PendingStats::read_slots(b.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        let z =
            PendingStats::read_slots(solo_order.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        assert_eq!(x, y, "step {step}: per-run masks are a function of the seeds");
        for run in 0..3 {
            let (x, z) = (x[run].unwrap().loss, z[run].unwrap().loss);
            if RUNS[run].prompt == P {
                // No padding: libtorch's CPU `bernoulli_` draws element after element from one
                // stream, so one draw over the sites is the sites drawn one after another.
                assert_eq!(x, z, "run {run} step {step}: unpadded run, the same masks");
            } else {
                assert_ne!(x, z, "run {run} step {step}: drawn at the pack's length");
            }
        }
    }
    let w = |e: &BatchedEngine| -> Vec<Tensor> {
        e.export(1).unwrap().weights.into_iter().map(|(_, t)| t).collect()
    };
    assert!(w(&a).iter().zip(w(&b)).all(|(x, y)| bit_equal(x, &y)));
}
