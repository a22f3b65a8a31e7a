//! `pdt_torch::bernoulli::bernoulli_cpu` (`csrc/bernoulli.cpp`): libtorch's `bernoulli_` bits on
//! the CPU, drawn in one loop. Where it draws (a CPU whose libtorch does not draw through MKL), the
//! mask and the generator's state afterwards must be libtorch's own; where it declines, nothing is
//! drawn. The process's generator is drawn from by this test alone: it holds the test binary's
//! libtorch lock (`pdt_testkit::process`).
#![allow(clippy::unwrap_used)] // a failed unwrap is a failed test

use pdt_torch::bernoulli::bernoulli_cpu;
use tch::{Device, Kind, Tensor};

fn empty(n: i64) -> Tensor {
    Tensor::empty([n], (Kind::Float, Device::Cpu))
}

#[test]
fn bernoulli_cpu_draws_libtorchs_bits_and_leaves_the_generator_where_libtorch_does() {
    let _g = pdt_testkit::process::libtorch();
    let mut drew = 0;
    // Sizes within one MT19937 block (624 outputs, two per element), across several, and the
    // size of a training step's dropout site; probabilities of the model's and the extremes.
    for (seed, n, p) in [
        (1, 1, 0.9),
        (2, 311, 0.9),
        (3, 313, 0.5),
        (4, 5000, 0.9),
        (5, 614_400, 0.9),
        (6, 999, 0.0),
        (7, 999, 1.0),
    ] {
        tch::manual_seed(seed);
        let _ = Tensor::rand([seed * 3], (Kind::Float, Device::Cpu)); // start mid-block
        let mut theirs = empty(n);
        let _ = theirs.bernoulli_float_(p);
        let after_theirs = Tensor::rand([5], (Kind::Float, Device::Cpu));

        tch::manual_seed(seed);
        let _ = Tensor::rand([seed * 3], (Kind::Float, Device::Cpu));
        let mut mine = empty(n);
        if !bernoulli_cpu(&mut mine, p) {
            // Declined: nothing drawn, so the generator's next draws are those before any mask.
            let mut again = empty(n);
            let _ = again.bernoulli_float_(p);
            assert!(again.equal(&theirs));
            continue;
        }
        drew += 1;
        let after_mine = Tensor::rand([5], (Kind::Float, Device::Cpu));
        let differ = mine.ne_tensor(&theirs).sum(Kind::Int64).int64_value(&[]);
        assert_eq!(differ, 0, "n = {n}, p = {p}: {differ} elements differ from bernoulli_");
        assert!(
            after_mine.equal(&after_theirs),
            "n = {n}: the generator is not where bernoulli_ leaves it"
        );
    }
    // A tensor it does not draw: not contiguous, or not float.
    let mut strided = Tensor::empty([4, 6], (Kind::Float, Device::Cpu)).transpose(0, 1);
    assert!(!bernoulli_cpu(&mut strided, 0.5));
    let mut double = Tensor::empty([8], (Kind::Double, Device::Cpu));
    assert!(!bernoulli_cpu(&mut double, 0.5));
    eprintln!("bernoulli_cpu drew {drew} of 7 cases (0 on a CPU whose libtorch draws through MKL)");
}
