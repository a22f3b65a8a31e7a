//! Parity with PyTorch: promptdt's forward pass, loss, gradients, clipping and AdamW steps against
//! golden fixtures written by `scripts/golden/make_prompt_dt_fixtures.py` (PyTorch 2.11.0, CPU) from
//! a PyTorch model written from the reference description (`scripts/golden/prompt_dt_torch.py`).
//!
//! Same weights, same inputs, same dropout seed (libtorch's CPU generator is shared by PyTorch and
//! tch; promptdt draws `at::dropout`'s noise, the same bits, through `pdt_model::dropout`), so on the
//! CPU that made the fixtures the results are compared
//! bit for bit. libtorch picks its kernels by instruction set, so fixtures made on another CPU are
//! compared within measured bounds (`support/golden.rs`): every test runs against the committed
//! fixtures and, when `make test` made them on this machine, against live ones bit for bit.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::golden;

use golden::{bounds, Golden};
use pdt_model::prompt_dt::Sequence;
use pdt_model::{checkpoint, PromptDt, PromptDtConfig, Segments};
use pdt_rundir::config::AdamWConfig;
use pdt_train::optim::AdamW;
use std::collections::HashMap;
use tch::{nn::VarStore, Device, Kind, Tensor};

fn read(set: &Golden, name: &str) -> HashMap<String, Tensor> {
    Tensor::read_safetensors(set.file(name)).expect("golden fixture readable").into_iter().collect()
}

/// Largest absolute difference between two tensors of the same shape.
fn max_diff(name: &str, got: &Tensor, want: &Tensor) -> f64 {
    assert_eq!(got.size(), want.size(), "{name}: shape");
    (got.to_kind(Kind::Double) - want.to_kind(Kind::Double)).abs().max().double_value(&[])
}

fn max_abs(t: &Tensor) -> f64 {
    t.to_kind(Kind::Double).abs().max().double_value(&[])
}

/// How far a result may be from the fixture when the fixture was made on another CPU.
#[derive(Clone, Copy)]
enum Bound {
    Abs(f64),
    /// Relative to the largest magnitude in the fixture's tensor.
    RelToMax(f64),
}

/// Collects every comparison against one fixture set, so a failure lists all that differ.
struct Check<'a> {
    set: &'a Golden,
    failures: Vec<String>,
    worst: f64,
}

impl<'a> Check<'a> {
    fn new(set: &'a Golden) -> Self {
        Self { set, failures: Vec::new(), worst: 0.0 }
    }

    /// Bit for bit on the fixture's own CPU, within `bound` elsewhere.
    fn close(&mut self, name: &str, got: &Tensor, want: &Tensor, bound: Bound) {
        let d = max_diff(name, got, want);
        let limit = match (self.set.bitwise, bound) {
            (true, _) => 0.0,
            (false, Bound::Abs(a)) => a,
            (false, Bound::RelToMax(r)) => r * max_abs(want),
        };
        if d > limit {
            self.failures
                .push(format!("{name}: differs from PyTorch by up to {d:e} (allowed {limit:e})"));
        }
        self.worst = self.worst.max(d);
    }

    fn finish(self, what: &str) {
        let how = if self.set.bitwise { "bit for bit" } else { "within the cross-CPU bounds" };
        assert!(
            self.failures.is_empty(),
            "{what} vs the {} fixtures ({}), expected {how}:\n{}",
            self.set.label,
            self.set.dir.display(),
            self.failures.join("\n")
        );
        eprintln!(
            "{what}: {} fixtures match {how} (largest difference {:e})",
            self.set.label, self.worst
        );
    }
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

// libtorch's random generator is global: tests that draw from it (init, dropout) run one at a time
// (with the other modules' tests: one lock for the test binary).
use pdt_testkit::process::LIBTORCH as TORCH_RNG;

/// Every test holds the lock while it builds a model (init draws from the generator).
fn lock() -> pdt_testkit::process::Alone {
    TORCH_RNG.lock().unwrap_or_else(|e| e.into_inner())
}

fn model(set: &Golden) -> (VarStore, PromptDt) {
    // The fixtures were made with torch.set_num_threads(1): reductions over the batch (bias and
    // weight gradients) split their partial sums by thread, so the thread count changes the last bit.
    tch::set_num_threads(1);
    let cfg = PromptDtConfig::reference(20, 6);
    let mut vs = VarStore::new(Device::Cpu);
    let m = PromptDt::new(&vs.root(), &cfg);
    checkpoint::load(&mut vs, &set.file("prompt_dt_state_dict.safetensors"), &cfg)
        .expect("weights load");
    (vs, m)
}

#[test]
fn parameter_count_is_the_reference_one() {
    let _rng = lock();
    let (vs, _) = model(&golden::sets()[0]);
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
fn eval_forward_matches_pytorch() {
    let _rng = lock();
    for set in golden::sets() {
        let (_vs, m) = model(&set);
        let inp = read(&set, "prompt_dt_inputs.safetensors");
        let exp = read(&set, "prompt_dt_expected.safetensors");
        let (h, p) = (segments(&inp, ""), segments(&inp, "prompt_"));
        m.check_inputs(&h, Some(&p)).expect("valid inputs");
        let mut check = Check::new(&set);
        let actions = Bound::Abs(bounds::ACTION_ABS);
        let preds = tch::no_grad(|| m.forward(&h, Sequence::eval(Some(&p))));
        check.close("eval.action_preds", &preds, &exp["eval.action_preds"], actions);
        let preds = tch::no_grad(|| m.forward(&h, Sequence::eval(None)));
        check.close(
            "eval_no_prompt.action_preds",
            &preds,
            &exp["eval_no_prompt.action_preds"],
            actions,
        );
        check.finish("eval forward");
    }
}

#[test]
fn training_steps_match_pytorch() {
    let _rng = lock();
    for set in golden::sets() {
        training_steps(&set);
    }
}

fn training_steps(set: &Golden) {
    let (vs, m) = model(set);
    let inp = read(set, "prompt_dt_inputs.safetensors");
    let exp = read(set, "prompt_dt_expected.safetensors");
    let (h, p) = (segments(&inp, ""), segments(&inp, "prompt_"));
    let mut opt = AdamW::new(&vs, &m.cfg.parameter_names(), AdamWConfig::default());
    let mut check = Check::new(set);
    let scalar = |t: &Tensor| t.double_value(&[]);
    tch::manual_seed(1234);
    for k in 1..=2u64 {
        let preds = m.forward(&h, Sequence::train(Some(&p)));
        let name = format!("train.{k}.action_preds");
        check.close(&name, &preds, &exp[&name], Bound::Abs(bounds::ACTION_ABS));
        let loss = PromptDt::action_loss(&preds, &h.actions, &h.mask);
        let name = format!("train.{k}.loss");
        check.close(&name, &loss, &exp[&name], Bound::RelToMax(bounds::SCALAR_REL));
        let mut grads = opt.backward(&loss);
        if k == 1 {
            let mut with_grad = 0;
            for (name, grad) in opt.param_names().zip(&grads.0) {
                let key = format!("train.1.grad.{name}");
                match (exp.get(&key), grad) {
                    (Some(want), Some(grad)) => {
                        check.close(&key, grad, want, Bound::RelToMax(bounds::GRAD_REL_TO_MAX));
                        with_grad += 1;
                    }
                    (None, None) => {}
                    (want, got) => {
                        panic!("{name}: PyTorch grad {}, ours {}", want.is_some(), got.is_some())
                    }
                }
            }
            assert!(with_grad > 50, "only {with_grad} gradients compared");
        }
        let norm = opt.clip_grad_norm(&mut grads, 0.25);
        let name = format!("train.{k}.grad_norm");
        let ours = norm;
        check.close(&name, &ours, &exp[&name], Bound::RelToMax(bounds::SCALAR_REL));
        let lr = opt.cfg.lr_at(k - 1);
        // The schedule is f64 arithmetic on both sides: equal on every CPU.
        assert_eq!(lr, scalar(&exp[&format!("train.lr.{k}")]), "train.lr.{k}");
        opt.step(&grads, lr);
    }
    for (name, var) in vs.variables() {
        let key = format!("train.2.param.{name}");
        check.close(&key, &var, &exp[&key], Bound::Abs(bounds::PARAM_ABS));
    }
    check.finish("two training steps");
}

#[test]
fn weights_round_trip_through_safetensors_with_reference_buffers() {
    let _rng = lock();
    let set = &golden::sets()[0];
    let (vs, _) = model(set);
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("w.safetensors");
    checkpoint::save(&vs, &path, &PromptDtConfig::reference(20, 6)).expect("save");
    let ours = Tensor::read_safetensors(&path).expect("readable");
    let theirs = read(set, "prompt_dt_state_dict.safetensors");
    assert_eq!(ours.len(), 67);
    for (name, t) in &ours {
        let want = &theirs[name];
        assert_eq!(t.kind(), want.kind(), "{name}: dtype");
        // No arithmetic: the same bits on every CPU.
        assert_eq!(
            max_diff(name, &t.to_kind(Kind::Double), &want.to_kind(Kind::Double)),
            0.0,
            "{name}"
        );
    }
}
