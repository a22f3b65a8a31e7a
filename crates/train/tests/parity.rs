//! Parity with PyTorch: promptdt's forward pass, loss, gradients, clipping and AdamW steps against
//! golden fixtures written by `scripts/golden/make_prompt_dt_fixtures.py` (PyTorch 2.11.0, CPU) from
//! a PyTorch model written from the reference description (`scripts/golden/prompt_dt_torch.py`).
//!
//! Same weights, same inputs, same dropout seed (libtorch's CPU generator is shared by PyTorch and
//! tch, and both call `at::dropout`), so the results are compared bit for bit.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_model::{checkpoint, PromptDt, PromptDtConfig, Segments};
use pdt_train::optim::{AdamW, AdamWConfig};
use std::collections::HashMap;
use std::path::PathBuf;
use tch::{nn::VarStore, Device, Kind, Tensor};

fn golden(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../testdata/golden").join(name)
}

fn read(name: &str) -> HashMap<String, Tensor> {
    Tensor::read_safetensors(golden(name)).expect("golden fixture readable").into_iter().collect()
}

/// Largest absolute difference between two tensors of the same shape.
fn max_diff(name: &str, got: &Tensor, want: &Tensor) -> f64 {
    assert_eq!(got.size(), want.size(), "{name}: shape");
    (got.to_kind(Kind::Double) - want.to_kind(Kind::Double)).abs().max().double_value(&[])
}

/// Bitwise equality, reporting the largest difference when it fails.
fn assert_same(name: &str, got: &Tensor, want: &Tensor) {
    let d = max_diff(name, got, want);
    assert!(d == 0.0, "{name}: differs from PyTorch by up to {d:e}");
}

fn segments(inp: &HashMap<String, Tensor>, prefix: &str) -> Segments {
    let g = |n: &str| inp[&format!("{prefix}{n}")].shallow_clone();
    let mask_name = if prefix.is_empty() {
        "attention_mask".to_string()
    } else {
        format!("{prefix}attention_mask")
    };
    Segments {
        states: g("states"),
        actions: g("actions"),
        returns_to_go: g("returns_to_go"),
        timesteps: g("timesteps"),
        mask: inp[&mask_name].to_kind(Kind::Float),
    }
}

/// libtorch's random generator is global: tests that draw from it (init, dropout) run one at a time.
static TORCH_RNG: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Every test holds the lock while it builds a model (init draws from the generator).
fn lock() -> std::sync::MutexGuard<'static, ()> {
    TORCH_RNG.lock().unwrap_or_else(|e| e.into_inner())
}

fn model() -> (VarStore, PromptDt) {
    // The fixtures were made with torch.set_num_threads(1): reductions over the batch (bias and
    // weight gradients) split their partial sums by thread, so the thread count changes the last bit.
    tch::set_num_threads(1);
    let cfg = PromptDtConfig::reference(20, 6);
    let mut vs = VarStore::new(Device::Cpu);
    let m = PromptDt::new(&vs.root(), &cfg);
    checkpoint::load(&mut vs, &golden("prompt_dt_state_dict.safetensors"), cfg.n_layer)
        .expect("weights load");
    (vs, m)
}

#[test]
fn parameter_count_is_the_reference_one() {
    let _rng = lock();
    let (vs, _) = model();
    let n: i64 = vs.trainable_variables().iter().map(Tensor::numel).map(|n| n as i64).sum();
    assert_eq!(n, 862_619);
    let mut names = PromptDtConfig::reference(20, 6).parameter_names();
    assert_eq!(names.len(), vs.variables().len());
    names.sort();
    assert!(names
        .iter()
        .zip(vs.variables().keys().collect::<std::collections::BTreeSet<_>>())
        .all(|(a, b)| a == b));
    assert_eq!(vs.variables().len() + 6, 67, "state_dict entries incl. 2 buffers per block");
}

#[test]
fn eval_forward_matches_pytorch_bitwise() {
    let _rng = lock();
    let (_vs, m) = model();
    let inp = read("prompt_dt_inputs.safetensors");
    let exp = read("prompt_dt_expected.safetensors");
    let (h, p) = (segments(&inp, ""), segments(&inp, "prompt_"));
    m.check_inputs(&h, Some(&p)).expect("valid inputs");
    let preds = tch::no_grad(|| m.forward(&h, Some(&p), false));
    assert_same("eval.action_preds", &preds, &exp["eval.action_preds"]);
    let preds = tch::no_grad(|| m.forward(&h, None, false));
    assert_same("eval_no_prompt.action_preds", &preds, &exp["eval_no_prompt.action_preds"]);
}

#[test]
fn training_steps_match_pytorch_bitwise() {
    let _rng = lock();
    let (vs, m) = model();
    let inp = read("prompt_dt_inputs.safetensors");
    let exp = read("prompt_dt_expected.safetensors");
    let (h, p) = (segments(&inp, ""), segments(&inp, "prompt_"));
    let mut opt = AdamW::new(&vs, &m.cfg.parameter_names(), AdamWConfig::default());
    tch::manual_seed(1234);
    for k in 1..=2u64 {
        let preds = m.forward(&h, Some(&p), true);
        assert_same(
            &format!("train.{k}.action_preds"),
            &preds,
            &exp[&format!("train.{k}.action_preds")],
        );
        let loss = PromptDt::action_loss(&preds, &h.actions, &h.mask);
        assert_same(&format!("train.{k}.loss"), &loss, &exp[&format!("train.{k}.loss")]);
        let mut grads = opt.backward(&loss);
        if k == 1 {
            let mut with_grad = 0;
            let mut diffs = Vec::new();
            for (name, grad) in opt.param_names().zip(&grads.0) {
                let key = format!("train.1.grad.{name}");
                match (exp.get(&key), grad) {
                    (Some(want), Some(grad)) => {
                        let d = max_diff(&key, grad, want);
                        if d != 0.0 {
                            diffs.push(format!("{name}: {d:e}"));
                        }
                        with_grad += 1;
                    }
                    (None, None) => {}
                    (want, got) => {
                        panic!("{name}: PyTorch grad {}, ours {}", want.is_some(), got.is_some())
                    }
                }
            }
            diffs.sort();
            assert!(diffs.is_empty(), "gradients differ from PyTorch:\n{}", diffs.join("\n"));
            assert!(with_grad > 50, "only {with_grad} gradients compared");
        }
        let norm = opt.clip_grad_norm(&mut grads, 0.25);
        let want_norm = exp[&format!("train.{k}.grad_norm")].double_value(&[]);
        assert_eq!(norm as f32, want_norm as f32, "train.{k}.grad_norm");
        let lr = opt.cfg.lr_at(k - 1);
        assert_eq!(lr, exp[&format!("train.lr.{k}")].double_value(&[]), "train.lr.{k}");
        opt.step(&grads, lr);
    }
    for (name, var) in vs.variables() {
        assert_same(&format!("train.2.param.{name}"), &var, &exp[&format!("train.2.param.{name}")]);
    }
}

#[test]
fn weights_round_trip_through_safetensors_with_reference_buffers() {
    let _rng = lock();
    let (vs, _) = model();
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("w.safetensors");
    checkpoint::save(&vs, &path, 3, 1024).expect("save");
    let ours = Tensor::read_safetensors(&path).expect("readable");
    let theirs = read("prompt_dt_state_dict.safetensors");
    assert_eq!(ours.len(), 67);
    for (name, t) in &ours {
        let want = &theirs[name];
        assert_eq!(t.kind(), want.kind(), "{name}: dtype");
        assert_same(name, &t.to_kind(Kind::Double), &want.to_kind(Kind::Double));
    }
}
