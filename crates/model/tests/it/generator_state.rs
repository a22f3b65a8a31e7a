//! `pdt_model::device::GeneratorState` (`csrc/generator.cpp`): libtorch's default generator put back
//! where it stood repeats the draws that followed, whatever drew in between. The test holds the test
//! binary's libtorch lock (`pdt_testkit::process`), so that no other test draws from the process's
//! generator meanwhile.
#![allow(clippy::unwrap_used)] // a failed unwrap is a failed test

use pdt_model::device::GeneratorState;
use tch::{Device, Kind, Tensor};

#[test]
fn a_generator_state_put_back_repeats_the_draws_after_it() {
    let _g = pdt_testkit::process::libtorch();
    tch::manual_seed(7);
    let _ = Tensor::rand([3], (Kind::Float, Device::Cpu));
    let state = GeneratorState::take(Device::Cpu).unwrap();
    let first = Tensor::rand([5], (Kind::Float, Device::Cpu));
    let dropout = Tensor::ones([64], (Kind::Float, Device::Cpu)).dropout(0.5, true);
    let _others = Tensor::rand([11], (Kind::Float, Device::Cpu)); // another run's draws
    state.restore().unwrap();
    let again = Tensor::rand([5], (Kind::Float, Device::Cpu));
    assert!(first.equal(&again), "{first} against {again}");
    // The sequence goes on from there: the same dropout mask, then fresh draws.
    assert!(dropout.equal(&Tensor::ones([64], (Kind::Float, Device::Cpu)).dropout(0.5, true)));
    let next = Tensor::rand([5], (Kind::Float, Device::Cpu));
    assert!(!first.equal(&next));
}
