//! A batched pack acting for its runs' evaluations (`PackEngine::act`, issue 30): each run's
//! actions are its solo model's (the eval-mode full forward at the last history step) within a
//! measured bound; they do not depend on which pack-mates act with it, on a pack-mate that
//! diverged, nor on the pack-mates' padded sizes; bad inputs are errors naming the run.
#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: a failed unwrap is a failed test

use crate::fixture;
use pdt_model::Segments;
use pdt_train::pack::{PackEngine, SlotAct};
use tch::Tensor;

use fixture::*;

/// The first `a` samples of `s`.
fn first(s: &Segments, a: i64) -> Segments {
    let n = |t: &Tensor| t.narrow(0, 0, a);
    Segments {
        states: n(&s.states),
        actions: n(&s.actions),
        returns_to_go: n(&s.returns_to_go),
        timesteps: n(&s.timesteps),
        mask: n(&s.mask),
    }
}

/// Run `run`'s forward of `a` episodes, padded to `rows`.
fn act_of(run: usize, a: i64, rows: i64) -> SlotAct {
    let b = batch(run, 9);
    SlotAct { history: first(&b.history, a), prompt: b.prompt.map(|p| first(&p, a)), rows }
}

fn acts(which: [Option<(i64, i64)>; 3]) -> Vec<Option<SlotAct>> {
    which.iter().enumerate().map(|(run, w)| w.map(|(a, rows)| act_of(run, a, rows))).collect()
}

#[test]
fn each_run_acts_as_its_solo_model() {
    let _g = lock();
    let mut e = engine();
    // Fewer episodes than the padded size, as in an evaluation's last window.
    let out = e.act(acts([Some((4, B as i64)), Some((5, B as i64)), Some((6, 8))])).unwrap();
    let mut worst: f64 = 0.0;
    for (run, got) in out.iter().enumerate() {
        let got = got.as_ref().expect("every run acted");
        let (_vs, model) = solo(run);
        let a = got.size()[0];
        let b = batch(run, 9);
        let (h, p) = (first(&b.history, a), b.prompt.as_ref().map(|p| first(p, a)));
        // The solo model's full forward, and its cached one (what a run's own evaluation uses).
        let full = tch::no_grad(|| model.forward(&h, p.as_ref(), false)).select(1, K as i64 - 1);
        let cached = tch::no_grad(|| {
            let prefix = p.as_ref().map(|p| model.prefix(p));
            model.act(&h, prefix.as_ref())
        });
        let (d_full, d_cached) = (max_diff(got, &full), max_diff(got, &cached));
        eprintln!(
            "run {run}: {a} episodes, max |pack - solo full| = {d_full:e}, cached {d_cached:e}"
        );
        worst = worst.max(d_full).max(d_cached);
    }
    // Measured (AMD EPYC with AVX-512, libtorch 2.11): against the full forward 0, 1.5e-8 and
    // 6e-8 for the three runs (the pack's masked prompt padding and its last block run for the
    // last token only change the summation order), the same against the cached one. The bound is
    // the training forward's (`pack_batched.rs`).
    assert!(worst <= 1e-6, "the pack's actions differ from solo by {worst:e}");
}

#[test]
fn a_run_acts_the_same_whoever_acts_with_it() {
    let _g = lock();
    let mut e = engine();
    let all = e.act(acts([Some((4, 6)), Some((6, 6)), Some((3, 6))])).unwrap();
    let alone = e.act(acts([Some((4, 6)), None, None])).unwrap();
    assert!(alone[1].is_none() && alone[2].is_none());
    // The others in another padded size: computed in a forward of their own.
    let apart = e.act(acts([Some((4, 6)), Some((6, 8)), Some((3, 8))])).unwrap();
    let mut poisoned = engine();
    let mut state = poisoned.export(2).unwrap();
    for (name, t) in &mut state.weights {
        if name.starts_with("transformer.h.0.attn.c_attn.weight") {
            *t = t.fill(f64::NAN);
        }
    }
    poisoned.import(2, state).unwrap();
    let with_nan = poisoned.act(acts([Some((4, 6)), Some((6, 6)), Some((3, 6))])).unwrap();
    let run0 = |out: &[Option<Tensor>]| out[0].as_ref().unwrap().shallow_clone();
    for (what, out) in
        [("alone", &alone), ("pack-mates apart", &apart), ("diverged pack-mate", &with_nan)]
    {
        assert!(bit_equal(&run0(out), &run0(&all)), "run 0's actions change {what}");
    }
    assert!(bit_equal(with_nan[1].as_ref().unwrap(), all[1].as_ref().unwrap()));
    let nan = with_nan[2].as_ref().unwrap();
    assert!(nan.isnan().any().int64_value(&[]) == 1, "the diverged run's actions are its NaNs");
}

#[test]
fn bad_forwards_are_refused_by_run() {
    let _g = lock();
    let mut e = engine();
    // More episodes than the padded size.
    let err = e.act(acts([Some((6, 4)), None, None])).unwrap_err().to_string();
    assert!(err.contains("run 0") && err.contains("acting holds 4 samples"), "{err}");
    // A prompt for the run without one.
    let mut bad = acts([None, Some((3, 6)), None]);
    if let Some(a) = bad[1].as_mut() {
        a.prompt = Some(first(&segments(5, P), 3));
    }
    let err = e.act(bad).unwrap_err().to_string();
    assert!(err.contains("run 1 uses no prompt, its evaluation's forward has one"), "{err}");
    // One request per run of the pack.
    let err = e.act(vec![None]).unwrap_err().to_string();
    assert!(err.contains("1 slot forwards for a pack of 3 runs"), "{err}");
}
