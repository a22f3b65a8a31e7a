//! `PromptDt::forward` with `Act` (cached prompt keys and values, no trailing action token, last
//! layer for the last position only) against the reference path, a `Sequence` forward at `K-1`.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::support;
use pdt_model::prompt_dt::{Act, Sequence};
use pdt_model::{PromptDt, PromptDtConfig, Segments};
use support::segments;
use tch::{nn::VarStore, Device, Kind, Tensor};

/// The rows `index` of every tensor of `s`.
fn rows(s: &Segments, index: &Tensor) -> Segments {
    Segments {
        states: s.states.index_select(0, index),
        actions: s.actions.index_select(0, index),
        returns_to_go: s.returns_to_go.index_select(0, index),
        timesteps: s.timesteps.index_select(0, index),
        mask: s.mask.index_select(0, index),
    }
}

/// Largest |act - forward[:, K-1]| for a model of `cfg` with `prompts` tasks.
fn max_diff(cfg: &PromptDtConfig, b: i64, k: i64, prompt_steps: Option<i64>, seed: i64) -> f64 {
    tch::manual_seed(seed);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), cfg);
    // Weights of a trained model's scale: the transformer weights of a Cheetah-Dir Prompt-DT
    // trained 2000 iterations have std 0.029-0.032 (init 0.02), so add N(0, 0.03) to every weight.
    tch::no_grad(|| {
        for (_, mut v) in vs.variables() {
            let _ = v.g_add_(&(Tensor::randn_like(&v) * 0.03));
        }
    });
    let (ds, da) = (cfg.state_dim as i64, cfg.act_dim as i64);
    let history = segments(b, k, ds, da);
    let tasks = 3;
    let task_of = Tensor::randint(tasks, [b], (Kind::Int64, Device::Cpu));
    let prompts = prompt_steps.map(|lp| segments(tasks, lp, ds, da));
    let per_sample = prompts.as_ref().map(|p| rows(p, &task_of));
    model.check_inputs(&history, per_sample.as_ref()).unwrap();
    let (full, fast) = tch::no_grad(|| {
        let full = model.forward(&history, Sequence::eval(per_sample.as_ref())).select(1, k - 1); // [B, da]
        let cache = prompts.as_ref().map(|p| model.prefix(p, None).select(&task_of));
        (full, model.forward(&history, Act { prompt: cache.as_ref(), lora: None }))
    });
    assert_eq!(fast.size(), vec![b, da]);
    (full - fast).abs().max().double_value(&[])
}

#[test]
fn act_equals_the_full_forward_at_the_last_step() {
    // One test: the cases draw from libtorch's global generator, which parallel tests would share.
    let _g = pdt_testkit::process::libtorch(); // the process's generator and thread count
    tch::set_num_threads(1);
    let cheetah = PromptDtConfig::reference(20, 6);
    let point = PromptDtConfig::reference(2, 2);
    let wide = PromptDtConfig { n_head: 2, n_layer: 4, ..PromptDtConfig::reference(11, 3) };
    let mut worst: f64 = 0.0;
    for (cfg, b, k, lp) in [
        (&cheetah, 1, 20, Some(5)),
        (&cheetah, 7, 20, Some(5)),
        (&cheetah, 64, 20, Some(5)),
        (&cheetah, 5, 20, None), // MT-ORL: no prompt
        (&cheetah, 3, 1, Some(1)),
        (&point, 50, 20, Some(5)),
        (&point, 4, 20, Some(20)), // prompt as long as the history
        (&wide, 9, 10, Some(4)),
    ] {
        for seed in 0..3 {
            let d = max_diff(cfg, b, k, lp, seed);
            eprintln!("state {} b {b} k {k} prompt {lp:?} seed {seed}: {d:e}", cfg.state_dim);
            worst = worst.max(d);
        }
    }
    eprintln!("largest |act - forward| over all cases: {worst:e}");
    assert!(worst < 1e-6, "{worst:e}");
}

/// An episode's action does not depend on the episodes batched with it (1 thread).
#[test]
fn act_is_the_same_alone_or_batched() {
    let _g = pdt_testkit::process::libtorch(); // the process's generator and thread count
    tch::set_num_threads(1);
    tch::manual_seed(11);
    let cfg = PromptDtConfig::reference(2, 2);
    let vs = VarStore::new(Device::Cpu);
    let model = PromptDt::new(&vs.root(), &cfg);
    let (b, k) = (8, 4);
    let history = segments(b, k, 2, 2);
    let prompts = segments(b, 5, 2, 2);
    let all = Tensor::arange(b, (Kind::Int64, Device::Cpu));
    let (batched, full_batched) = tch::no_grad(|| {
        let c = model.prefix(&prompts, None);
        (
            model.forward(&history, Act { prompt: Some(&c.select(&all)), lora: None }),
            model.forward(&history, Sequence::eval(Some(&prompts))).select(1, k - 1),
        )
    });
    let np = tch::no_grad(|| model.forward(&history, Act { prompt: None, lora: None }));
    let mut same_np = 0;
    for i in 0..b {
        let one = Tensor::from_slice(&[i]);
        let alone =
            tch::no_grad(|| model.forward(&rows(&history, &one), Act { prompt: None, lora: None }));
        same_np += i64::from(alone.equal(&np.get(i).unsqueeze(0)));
    }
    eprintln!("no prompt: {same_np} of {b}");
    let mut same = 0;
    let mut same_full = 0;
    for i in 0..b {
        let one = Tensor::from_slice(&[i]);
        let h = rows(&history, &one);
        let p = rows(&prompts, &one);
        let (alone, full_alone) = tch::no_grad(|| {
            (
                model.forward(&h, Act { prompt: Some(&model.prefix(&p, None)), lora: None }),
                model.forward(&h, Sequence::eval(Some(&p))).select(1, k - 1),
            )
        });
        same += i64::from(alone.equal(&batched.get(i).unsqueeze(0)));
        same_full += i64::from(full_alone.equal(&full_batched.get(i).unsqueeze(0)));
    }
    eprintln!("act: {same} of {b} bit-identical alone and batched; forward: {same_full} of {b}");
    if pdt_testkit::cpu::batch_invariant() {
        assert_eq!(same, b);
    } else {
        // AVX-512 kernels depend on the batch size (pdt_testkit::cpu::batch_invariant).
        for i in 0..b {
            let one = Tensor::from_slice(&[i]);
            let h = rows(&history, &one);
            let p = rows(&prompts, &one);
            let alone = tch::no_grad(|| {
                model.forward(&h, Act { prompt: Some(&model.prefix(&p, None)), lora: None })
            });
            let d = (alone - batched.get(i).unsqueeze(0)).abs().max().double_value(&[]);
            assert!(d <= f64::from(pdt_testkit::cpu::BATCH_TOLERANCE), "row {i}: {d:e}");
        }
    }
}
