//! The batched pack engine (`pdt_pack::BatchedEngine`) against solo runs: weights
//! read out as solo checkpoints, the forward pass of each run of a pack, 50 training steps of a pack
//! of 3 against 3 solo `train_step` loops, and the independence of a run from its pack-mates.
//!
//! Batches are random tensors of the sampler's shapes (left-padded histories and prompts, timesteps
//! in range), on a small model with two heads so that every reshape of the attention is exercised.
#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: a failed unwrap is a failed test

use crate::fixture;
use pdt_base::seed::derive_seed;
use pdt_model::dropout::Dropout;
use pdt_model::prompt_dt::Sequence;
use pdt_model::{PromptDt, PromptDtConfig, Segments};
use pdt_pack::model::{DropoutSeeds, PackedBatch, PackedRow};
use pdt_pack::{BatchedEngine, PackEngine, PackLayout, SlotSpec, SlotStep};
use pdt_rundir::config::AdamWConfig;
use pdt_rundir::config::LossOn;
use pdt_train::optim::SlotState;
use pdt_train::optim::{AdamW, Optimizer};
use pdt_train::step::{train_step, DeviceBatch, PendingStats, StepStats};
use tch::{nn::VarStore, Device, Kind, Tensor};

use fixture::*;

#[test]
fn fresh_slots_hold_the_solo_initial_weights_and_round_trip() {
    let _g = lock();
    let mut e = engine();
    for run in 0..3 {
        let (vs, _) = solo(run);
        let vars = vs.variables();
        let state = e.export(run).unwrap();
        assert_eq!(state.weights.len(), vars.len(), "every solo parameter, nothing else");
        let names: Vec<&String> = state.weights.iter().map(|(n, _)| n).collect();
        assert_eq!(names, cfg().parameter_names().iter().collect::<Vec<_>>(), "state_dict order");
        for (name, t) in &state.weights {
            assert!(bit_equal(t, &vars[name]), "run {run}: {name} is not the solo initial weight");
        }
        assert!(state.moments.is_empty(), "a fresh run has no optimiser state");
    }
    // Two steps give moments; export(import(x)) == x, and a slot imported into another slot is
    // that slot from then on.
    for step in 0..2 {
        e.step(steps_of(step, [true; 3])).unwrap();
    }
    let s0 = e.export(0).unwrap();
    assert!(!s0.moments.is_empty());
    e.import(0, e.export(0).unwrap()).unwrap();
    assert_same_state("re-imported slot 0", &e.export(0).unwrap(), &s0);
    let s1 = e.export(1).unwrap();
    assert!(s1.moments.keys().all(|n| !n.starts_with("prompt_")), "MT-ORL: no prompt moments");
    e.import(2, e.export(0).unwrap()).unwrap();
    assert_same_state("slot 0 copied into slot 2", &e.export(2).unwrap(), &s0);
    assert_same_state("slot 1 untouched by imports", &e.export(1).unwrap(), &s1);
    // A malformed state is refused.
    let mut bad = e.export(0).unwrap();
    bad.weights.pop();
    assert!(e.import(1, bad).is_err());
}

/// Each run's predictions from the pack, `[B, Lp+K, da]` (its own steps).
fn packed_preds(e: &BatchedEngine, step: u64, train: bool) -> Vec<Tensor> {
    let batches: Vec<DeviceBatch> = (0..3).map(|i| batch(i, step)).collect();
    let rows: Vec<Option<PackedRow<'_>>> = batches
        .iter()
        .map(|b| Some(PackedRow { history: &b.history, prompt: b.prompt.as_ref() }))
        .collect();
    let model = e.model();
    let pb =
        PackedBatch::new(&rows, B as i64, K as i64, P as i64, &model.cfg, Device::Cpu).unwrap();
    let seeds = DropoutSeeds(
        RUNS.iter().map(|r| Some(derive_seed(r.seed, STREAM_DROPOUT, step) as i64)).collect(),
    );
    let all = tch::no_grad(|| model.forward_all_steps(&pb, train.then_some(&seeds))); // [3, B, P+K, da]
    (0..3)
        .map(|i| {
            let own = (RUNS[i].prompt + K) as i64;
            all.get(i as i64).narrow(1, (P + K) as i64 - own, own)
        })
        .collect()
}

#[test]
fn each_run_of_a_pack_predicts_as_solo() {
    let _g = lock();
    let e = engine();
    let mut worst: f64 = 0.0;
    for train in [false, true] {
        let packed = packed_preds(&e, 3, train);
        for (run, got) in packed.iter().enumerate() {
            let (_vs, model) = solo(run);
            let b = batch(run, 3);
            if train {
                tch::manual_seed(derive_seed(RUNS[run].seed, STREAM_DROPOUT, 3) as i64);
            }
            let want = tch::no_grad(|| {
                model.forward(
                    &b.history,
                    Sequence::new(b.prompt.as_ref(), Dropout::train(train)).all_steps(),
                )
            });
            // Real steps only: a padded step's prediction is read by nothing (the loss masks it,
            // attention gives it weight 0), and it differs, since a padded query attends to the
            // pack's extra padding as well (every key of its row is masked).
            let mask = match &b.prompt {
                Some(p) => Tensor::cat(&[&p.mask, &b.history.mask], 1),
                None => b.history.mask.shallow_clone(),
            }
            .gt(0.0)
            .unsqueeze(-1); // [B, Lp+K, 1]
            let d =
                max_diff(&got.where_scalarother(&mask, 0.0), &want.where_scalarother(&mask, 0.0));
            eprintln!("run {run} (train {train}): max |packed - solo| over real steps = {d:e}");
            worst = worst.max(d);
        }
    }
    // (The pack's last block runs for the state tokens only, the solo model's on every token.)
    // Measured (AVX-512 CPU, libtorch 2.11): 0 for runs 0 and 2, 6e-8 for run 1 (no prompt:
    // 3P extra padded keys change the softmax's summation order), in eval and train mode (so the
    // dropout masks are solo's: a different mask would differ by O(0.1)). Bound ~15x that.
    assert!(worst <= 1e-6, "packed predictions differ from solo by {worst:e}");
}

/// 50 steps of the pack against 3 solo `train_step` loops (same batches, same dropout seeding).
#[test]
fn fifty_pack_steps_match_three_solo_runs() {
    let _g = lock();
    const STEPS: u64 = 50;
    let mut e = engine();
    let mut packed: Vec<Vec<StepStats>> = vec![Vec::new(); 3];
    for step in 0..STEPS {
        let out = PendingStats::read_slots(e.step(steps_of(step, [true; 3])).unwrap()).unwrap();
        for (i, st) in out.into_iter().enumerate() {
            packed[i].push(st.expect("every run was stepped"));
        }
    }
    let (mut loss_d, mut norm_d, mut w_d): (f64, f64, f64) = (0.0, 0.0, 0.0);
    for run in 0..3 {
        let (vs, model) = solo(run);
        let init: Vec<(String, Tensor)> =
            vs.variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
        let mut opt = Optimizer::PerTensor(AdamW::new(&vs, &cfg().parameter_names(), optim()));
        for step in 0..STEPS {
            tch::manual_seed(derive_seed(RUNS[run].seed, STREAM_DROPOUT, step) as i64);
            let st =
                train_step(&model, &mut opt, &batch(run, step), RUNS[run].loss_on, step).unwrap();
            let p = &packed[run][step as usize];
            assert_eq!(p.lr, st.lr, "run {run} step {step}: learning rate");
            loss_d = loss_d.max((p.loss - st.loss).abs());
            norm_d = norm_d.max((p.grad_norm - st.grad_norm).abs() / st.grad_norm);
        }
        let state = e.export(run).unwrap();
        let vars = vs.variables();
        for (name, t) in &state.weights {
            let untouched = name.starts_with("transformer.wte")
                || name.starts_with("predict_state")
                || name.starts_with("predict_return")
                || (RUNS[run].prompt == 0 && name.starts_with("prompt_"));
            if untouched {
                let first = &init.iter().find(|(n, _)| n == name).unwrap().1;
                assert!(bit_equal(t, first), "run {run}: {name} is never read and must not move");
            }
            w_d = w_d.max(max_diff(t, &vars[name]));
        }
        let names: Vec<&String> = adam(&opt).state.keys().collect();
        assert_eq!(state.moments.keys().collect::<Vec<_>>(), names, "run {run}: moments");
        for (name, st) in &adam(&opt).state {
            assert_eq!(state.moments[name].step, st.step, "run {run}: {name} step count");
        }
    }
    eprintln!(
        "50 steps: max |loss diff| {loss_d:e}, max rel grad-norm diff {norm_d:e}, \
         max |weight diff| {w_d:e}"
    );
    // Measured (AVX-512 CPU, libtorch 2.11, 2 threads): losses 1.2e-7, gradient norms 2.1e-7
    // relative, final weights 1.5e-6 (after 50 AdamW steps at lr 1e-3). The per-run reductions
    // (masked mean, gradient norms) and the padded softmax round differently from solo's; the
    // forward products agree bit for bit. Bounds ~10x the measured.
    assert!(loss_d <= 2e-6, "losses differ from solo by {loss_d:e}");
    assert!(norm_d <= 3e-6, "gradient norms differ from solo by {norm_d:e} (relative)");
    assert!(w_d <= 2e-5, "final weights differ from solo by {w_d:e}");
}

#[test]
fn a_run_does_not_depend_on_its_pack_mates() {
    assert_runs_independent(&engine);
}

/// A solo run's state imported into a slot (a resumed run) continues as the solo run continues.
#[test]
fn an_imported_solo_state_continues_as_solo() {
    let _g = lock();
    let run = 2; // a shorter prompt, loss on prompt and history
    let (vs, model) = solo(run);
    let mut opt = Optimizer::PerTensor(AdamW::new(&vs, &cfg().parameter_names(), optim()));
    let solo_step = |opt: &mut Optimizer, step: u64| {
        tch::manual_seed(derive_seed(RUNS[run].seed, STREAM_DROPOUT, step) as i64);
        train_step(&model, opt, &batch(run, step), RUNS[run].loss_on, step).unwrap()
    };
    for step in 0..5 {
        solo_step(&mut opt, step);
    }
    let vars = vs.variables();
    let state = SlotState {
        weights: cfg()
            .parameter_names()
            .into_iter()
            .map(|n| {
                let t = vars[&n].detach().copy();
                (n, t)
            })
            .collect(),
        moments: adam(&opt)
            .state
            .iter()
            .map(|(n, st)| {
                let st = pdt_train::optim::ParamState {
                    step: st.step,
                    exp_avg: st.exp_avg.copy(),
                    exp_avg_sq: st.exp_avg_sq.copy(),
                };
                (n.clone(), st)
            })
            .collect(),
    };
    let mut e = engine();
    e.import(run, state).unwrap();
    let mut loss_d: f64 = 0.0;
    for step in 5..10 {
        let mut steps: Vec<Option<SlotStep>> = (0..3).map(|_| None).collect();
        steps[run] = Some(SlotStep { step, batch: batch(run, step) });
        let packed = PendingStats::read_slots(e.step(steps).unwrap()).unwrap()[run].unwrap();
        let st = solo_step(&mut opt, step);
        assert_eq!(packed.lr, st.lr);
        loss_d = loss_d.max((packed.loss - st.loss).abs());
    }
    let out = e.export(run).unwrap();
    let vars = vs.variables();
    let w_d = out.weights.iter().map(|(n, t)| max_diff(t, &vars[n])).fold(0.0, f64::max);
    for (name, st) in &adam(&opt).state {
        assert_eq!(out.moments[name].step, st.step, "{name}: step count carried over");
    }
    eprintln!("resumed in a pack: max |loss diff| {loss_d:e}, max |weight diff| {w_d:e}");
    // Measured: loss 3e-8, weights 6e-8 after 5 steps (the bounds of the 50-step test apply).
    assert!(loss_d <= 2e-6 && w_d <= 2e-5, "loss {loss_d:e}, weights {w_d:e}");
}

#[test]
fn mismatched_inputs_are_refused() {
    let _g = lock();
    let mut e = engine();
    // Run 1 uses no prompt but is given one.
    let mut steps = steps_of(0, [true; 3]);
    if let Some(s) = steps[1].as_mut() {
        s.batch.prompt = Some(segments(5, 2));
    }
    assert!(e.step(steps).is_err());
    // A prompt longer than the pack's.
    let mut steps = steps_of(0, [true; 3]);
    if let Some(s) = steps[0].as_mut() {
        s.batch.prompt = Some(segments(5, P + 1));
    }
    assert!(e.step(steps).is_err());
    assert!(e.step(steps_of(0, [true; 3]).into_iter().take(2).collect()).is_err());
    let mut mixed = specs();
    mixed[2].model.hidden_size = 16;
    assert!(BatchedEngine::new(mixed, layout(), Device::Cpu).is_err());
    // One computation for the pack: its runs' `train.last_block` must resolve alike (`auto`
    // resolves to the state tokens in a batched pack, so it goes with `state_tokens`).
    let mut mixed = specs();
    mixed[1].last_block = pdt_rundir::config::LastBlockChoice::AllTokens;
    let e = BatchedEngine::new(mixed, layout(), Device::Cpu).err().unwrap().to_string();
    assert!(e.contains("run 1's train.last_block (all_tokens) differs from run 0's (auto)"), "{e}");
    let mut alike = specs();
    alike[1].last_block = pdt_rundir::config::LastBlockChoice::StateTokens;
    assert!(BatchedEngine::new(alike, layout(), Device::Cpu).is_ok());
}

/// This thread's time on a CPU, in milliseconds (`/proc/thread-self/schedstat`, Linux): unlike
/// wall time, it leaves out the time other processes of a busy machine hold the cores.
fn on_cpu_ms() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|n| n.parse::<f64>().ok()))
        .map_or(f64::NAN, |ns| ns / 1e6)
}

/// Time of a pack of 3 against 3 solo steps, the reference architecture (state 20, action 6,
/// K = 20, a 5-step prompt), with the forward pass alone beside the whole step; wall time and
/// on-CPU time (1 thread: libtorch works on the calling thread). A measurement, not a check:
/// `cargo test --release -p pdt-pack --test it pack_batched:: -- --ignored --nocapture`.
#[test]
#[ignore]
fn time_pack_of_three_against_three_solo_steps() {
    let _g = lock();
    let threads: i32 = std::env::var("PACK_THREADS").ok().and_then(|t| t.parse().ok()).unwrap_or(1);
    tch::set_num_threads(threads);
    let steps: u64 = std::env::var("PACK_STEPS").ok().and_then(|t| t.parse().ok()).unwrap_or(12);
    let mcfg = PromptDtConfig::reference(20, 6);
    for b in [16usize, 64] {
        let (k, p) = (20usize, 5usize);
        let seg = |seed: u64, t: usize| {
            tch::manual_seed(seed as i64);
            let (ds, da) = (20i64, 6i64);
            let (bb, tt) = (b as i64, t as i64);
            let f = (Kind::Float, Device::Cpu);
            Segments {
                states: Tensor::randn([bb, tt, ds], f),
                actions: Tensor::rand([bb, tt, da], f) * 2.0 - 1.0,
                returns_to_go: Tensor::rand([bb, tt, 1], f),
                timesteps: Tensor::randint_low(0, 900, [bb, tt], (Kind::Int64, Device::Cpu)),
                mask: Tensor::ones([bb, tt], f),
            }
        };
        let batch = |run: u64, step: u64| DeviceBatch {
            history: seg(100 * run + step, k),
            prompt: Some(seg(100 * run + step + 50, p)),
        };
        let specs: Vec<SlotSpec> = (0..3)
            .map(|seed| SlotSpec {
                model: mcfg.clone(),
                uses_prompt: true,
                loss_on: LossOn::History,
                optim: AdamWConfig::default(),
                last_block: pdt_rundir::config::LastBlockChoice::Auto,
                seed,
            })
            .collect();
        let layout = PackLayout { batch_size: b, history_len: k, prompt_len: p };
        let mut e = BatchedEngine::new(specs, layout, Device::Cpu).unwrap();
        let solos: Vec<(VarStore, PromptDt)> = (0..3)
            .map(|seed| {
                tch::manual_seed(derive_seed(seed, STREAM_INIT, 0) as i64);
                let vs = VarStore::new(Device::Cpu);
                let m = PromptDt::new(&vs.root(), &mcfg);
                (vs, m)
            })
            .collect();
        let mut opts: Vec<Optimizer> = solos
            .iter()
            .map(|(vs, _)| {
                Optimizer::PerTensor(AdamW::new(
                    vs,
                    &mcfg.parameter_names(),
                    AdamWConfig::default(),
                ))
            })
            .collect();
        // Medians of wall and on-CPU milliseconds, the first 2 steps left out (warm-up).
        let median = |v: &[(f64, f64)]| {
            let mut w: Vec<f64> = v[2..].iter().map(|x| x.0).collect();
            let mut c: Vec<f64> = v[2..].iter().map(|x| x.1).collect();
            w.sort_by(f64::total_cmp);
            c.sort_by(f64::total_cmp);
            (w[w.len() / 2], c[c.len() / 2])
        };
        let (mut pack, mut solo, mut pack_fwd, mut solo_fwd) = (vec![], vec![], vec![], vec![]);
        for step in 0..steps {
            let steps: Vec<Option<SlotStep>> =
                (0..3).map(|r| Some(SlotStep { step, batch: batch(r, step) })).collect();
            let (t0, c0) = (std::time::Instant::now(), on_cpu_ms());
            e.step(steps).unwrap();
            pack.push((t0.elapsed().as_secs_f64() * 1e3, on_cpu_ms() - c0));
            let batches: Vec<DeviceBatch> = (0..3).map(|r| batch(r, step)).collect();
            let (t0, c0) = (std::time::Instant::now(), on_cpu_ms());
            for (r, ((_, m), opt)) in solos.iter().zip(&mut opts).enumerate() {
                tch::manual_seed(derive_seed(r as u64, STREAM_DROPOUT, step) as i64);
                train_step(m, opt, &batches[r], LossOn::History, step).unwrap();
            }
            solo.push((t0.elapsed().as_secs_f64() * 1e3, on_cpu_ms() - c0));
            // Forward (train mode) alone.
            let rows: Vec<Option<PackedRow<'_>>> = batches
                .iter()
                .map(|x| Some(PackedRow { history: &x.history, prompt: x.prompt.as_ref() }))
                .collect();
            let seeds = DropoutSeeds((0..3).map(|r| Some(r as i64 + step as i64)).collect());
            let (t0, c0) = (std::time::Instant::now(), on_cpu_ms());
            let model = e.model();
            let pb = PackedBatch::new(&rows, b as i64, k as i64, p as i64, &model.cfg, Device::Cpu)
                .unwrap();
            let _ = tch::no_grad(|| model.forward_all_steps(&pb, Some(&seeds)));
            pack_fwd.push((t0.elapsed().as_secs_f64() * 1e3, on_cpu_ms() - c0));
            let (t0, c0) = (std::time::Instant::now(), on_cpu_ms());
            for (r, (_, m)) in solos.iter().enumerate() {
                tch::manual_seed(r as i64 + step as i64);
                let x = &batches[r];
                let _ = tch::no_grad(|| m.forward(&x.history, Sequence::train(x.prompt.as_ref())));
            }
            solo_fwd.push((t0.elapsed().as_secs_f64() * 1e3, on_cpu_ms() - c0));
        }
        let (pk, so) = (median(&pack), median(&solo));
        let (pf, sf) = (median(&pack_fwd), median(&solo_fwd));
        eprintln!(
            "b{b}, {threads} thread(s), per step of all 3 runs: pack {:.1} ms wall / {:.1} ms on \
             CPU, 3 solo steps {:.1} / {:.1} (solo/pack {:.2}x wall, {:.2}x CPU); forward alone: \
             pack {:.1} / {:.1}, solo {:.1} / {:.1}",
            pk.0,
            pk.1,
            so.0,
            so.1,
            so.0 / pk.0,
            so.1 / pk.1,
            pf.0,
            pf.1,
            sf.0,
            sf.1
        );
    }
}

/// The pack's hub steps the engine from its own thread (`Box<dyn PackEngine + Send>`).
#[test]
fn the_engine_can_move_to_another_thread() {
    fn send<T: Send>() {}
    send::<BatchedEngine>();
}
