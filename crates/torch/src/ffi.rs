//! The C++ functions of `csrc/` (compiled by build.rs against the linked libtorch's headers: what
//! promptdt needs of libtorch that tch does not bind), and the one way to call them. Each catches
//! every C++ exception (`csrc/guard.h`) and reports it as -1 with a message.
#![allow(unsafe_code)]

use std::ffi::{c_char, c_int, c_void};

/// Receives the profiler's events: (context, name, kind, duration in ns).
pub(crate) type Sink = extern "C" fn(*mut c_void, *const c_char, c_int, u64);

unsafe extern "C" {
    pub(crate) fn pdt_set_cublas_tf32(on: c_int, err: *mut u8, err_len: usize) -> c_int;
    pub(crate) fn pdt_cublas_tf32(err: *mut u8, err_len: usize) -> c_int;
    /// `prev` receives 3 ints that `pdt_autocast_exit` takes back.
    pub(crate) fn pdt_autocast_enter(
        cuda: c_int,
        prev: *mut c_int,
        err: *mut u8,
        err_len: usize,
    ) -> c_int;
    pub(crate) fn pdt_autocast_exit(
        cuda: c_int,
        prev: *const c_int,
        err: *mut u8,
        err_len: usize,
    ) -> c_int;
    pub(crate) fn pdt_autocast_enabled(cuda: c_int, err: *mut u8, err_len: usize) -> c_int;
    pub(crate) fn pdt_profiler_start(with_cuda: c_int, err: *mut u8, err_len: usize) -> c_int;
    pub(crate) fn pdt_profiler_stop(
        ctx: *mut c_void,
        sink: Sink,
        err: *mut u8,
        err_len: usize,
    ) -> c_int;
    /// `self` and `out` are tch's tensor handles (`at::Tensor*`); `*out` is a new one the caller owns.
    pub(crate) fn pdt_pin_memory(
        tensor: *const c_void,
        out: *mut *mut c_void,
        err: *mut u8,
        err_len: usize,
    ) -> c_int;
    /// Fills `tensor` (a tch handle) with `bernoulli_(p)`'s bits: 1 if drawn, 0 if not (use
    /// `bernoulli_`).
    pub(crate) fn pdt_bernoulli_cpu(
        tensor: *mut c_void,
        p: f64,
        err: *mut u8,
        err_len: usize,
    ) -> c_int;
}

/// Calls `f` with a message buffer (pointer, length) for a `csrc/` function: its answer (>= 0), or
/// the C++ exception's message.
pub(crate) fn call(f: impl FnOnce(*mut u8, usize) -> c_int) -> Result<c_int, String> {
    let mut err = [0u8; 1024];
    let rc = f(err.as_mut_ptr(), err.len());
    if rc >= 0 {
        return Ok(rc);
    }
    let end = err.iter().position(|&b| b == 0).unwrap_or(err.len());
    Err(String::from_utf8_lossy(&err[..end]).into_owned())
}
