//! `train.last_block` through the real binary: a CPU run with the last block for the state tokens
//! only (`state_tokens`, the CUDA default) trains as the default run (`auto`: every token on the
//! CPU) within float rounding, records the choice, and resumes byte for byte.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{action_losses, losses, ok, s, tiny_setup, train, variant};

#[test]
fn state_tokens_train_as_all_tokens_within_rounding_and_resume_byte_for_byte() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let (all, states) = (tmp.path().join("all"), tmp.path().join("states"));
    train(&cfg, &all, &[]);
    let cfg_states = variant(&cfg, "train", "last_block", "\"state_tokens\"");
    train(&cfg_states, &states, &[]);
    let recorded = std::fs::read_to_string(states.join("config.toml")).unwrap();
    assert!(recorded.contains("last_block = \"state_tokens\""), "{recorded}");
    let default = std::fs::read_to_string(all.join("config.toml")).unwrap();
    assert!(!default.contains("last_block"), "the default is not written");

    let (a, b) = (action_losses(&all), action_losses(&states));
    assert_eq!(a.len(), b.len());
    assert!(!a.is_empty());
    let worst = a.iter().zip(&b).map(|(x, y)| ((x - y) / x).abs()).fold(0.0, f64::max);
    eprintln!("{} logged losses, max relative difference {worst:e}", a.len());
    // Measured (AMD EPYC, AVX2 kernels, 1 thread): 0 over the 8 logged losses (the drawn masks
    // are the full forward's, and this tiny model's gradients round alike). Another CPU's kernels
    // may round a product of fewer rows otherwise: bound 1e-5 relative.
    assert!(worst <= 1e-5, "losses differ by {worst:e} (relative)");

    // Stopped after iteration 4, resumed to 8: the same training as straight through.
    let resumed = tmp.path().join("resumed");
    train(&cfg_states, &resumed, &["--iterations", "4"]);
    ok(&["train", "--resume", s(&resumed), "--iterations", "8", "--quiet"]);
    assert_eq!(losses(&resumed), losses(&states), "resumed run: metrics");
}
