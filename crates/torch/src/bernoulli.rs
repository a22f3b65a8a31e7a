//! `bernoulli_(p)` on the CPU with libtorch's own bits, drawn faster (`csrc/bernoulli.cpp`): the
//! source of dropout's noise (`pdt_model::dropout`) and of a pack's per-run masks.

use tch::{Device, Kind, Tensor};

/// `t.bernoulli_(p)`: the same bits, through [`bernoulli_cpu`] where it draws them.
pub fn bernoulli_(t: &mut Tensor, p: f64) {
    if !bernoulli_cpu(t, p) {
        let _ = t.bernoulli_float_(p);
    }
}

/// `noise.bernoulli_(p)` for a contiguous float tensor on the CPU, libtorch's own bits drawn a block
/// of its MT19937 state at a time (`csrc/bernoulli.cpp`, 5x faster: libtorch's element-by-element
/// loop on a CPU other than Intel's was a tenth of a training step). False, with nothing drawn,
/// where that is not what `bernoulli_` draws on this machine (an Intel CPU draws through MKL) or
/// for any other tensor: then call `bernoulli_`.
pub fn bernoulli_cpu(noise: &mut Tensor, p: f64) -> bool {
    if noise.device() != Device::Cpu || noise.kind() != Kind::Float {
        return false;
    }
    // SAFETY: `noise.as_mut_ptr()` is a live tch tensor handle (`at::Tensor*`) for the call; the
    // C++ side checks it is a contiguous float CPU tensor and writes its elements only.
    #[allow(unsafe_code)]
    let fill =
        |err, len| unsafe { crate::ffi::pdt_bernoulli_cpu(noise.as_mut_ptr().cast(), p, err, len) };
    // An error (none is expected: the C++ side only checks and fills) leaves the draw to libtorch.
    matches!(crate::ffi::call(fill), Ok(1))
}
