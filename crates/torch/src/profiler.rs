//! libtorch's own profiler (Kineto) around a piece of work: every operator it dispatched and, on
//! CUDA, every kernel it launched, with their durations. tch 0.24 does not bind it;
//! `csrc/profiler.cpp` does. `promptdt bench --profile` counts with it what a training step runs
//! (`pdt_bench`'s profile). One profiler per process at a time: [`start`] while one runs is an
//! error (libtorch would quietly replace the running one's collection).

use std::ffi::{c_char, c_int, c_void, CStr};
use std::sync::atomic::{AtomicBool, Ordering};

/// Whether a [`Profiling`] is running in this process.
static ACTIVE: AtomicBool = AtomicBool::new(false);

/// What a recorded event is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    /// An operator dispatched on the host (`aten::addmm`; nested ones too: `aten::linear` and the
    /// `aten::addmm` it calls are two events).
    Op,
    /// A kernel run on a GPU.
    Kernel,
    /// A copy to, from or on a GPU.
    Memcpy,
    Memset,
    /// A CUDA runtime or driver call on the host (`cudaLaunchKernel`, ...).
    CudaApi,
    Other,
}

impl EventKind {
    fn from_code(code: c_int) -> Self {
        match code {
            0 => Self::Op,
            1 => Self::Kernel,
            2 => Self::Memcpy,
            3 => Self::Memset,
            4 => Self::CudaApi,
            _ => Self::Other,
        }
    }
}

/// One recorded event.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Event {
    pub name: String,
    pub kind: EventKind,
    pub duration_ns: u64,
}

#[derive(Debug, thiserror::Error)]
#[error("libtorch's profiler: {0}")]
pub struct ProfilerError(String);

/// A running profiler; [`Profiling::stop`] gives its events. Dropped without `stop`, it stops and
/// discards them.
#[derive(Debug)]
pub struct Profiling {
    stopped: bool,
}

/// Starts libtorch's profiler for this process's host operators, and with `cuda` also for its CUDA
/// kernels, copies and runtime calls.
pub fn start(cuda: bool) -> Result<Profiling, ProfilerError> {
    if ACTIVE.swap(true, Ordering::SeqCst) {
        return Err(ProfilerError("one is running in this process already".into()));
    }
    // SAFETY: the C++ function catches every exception and writes at most `len` bytes.
    #[allow(unsafe_code)]
    let start = |err, len| unsafe { crate::ffi::pdt_profiler_start(c_int::from(cuda), err, len) };
    match crate::ffi::call(start) {
        Ok(_) => Ok(Profiling { stopped: false }),
        Err(m) => {
            ACTIVE.store(false, Ordering::SeqCst);
            Err(ProfilerError(m))
        }
    }
}

/// Receives the events from C++: `ctx` is the `Vec<Event>` of `stop`. It must not unwind into C++,
/// so a panic (an allocation failure) is caught and the event dropped.
extern "C" fn sink(ctx: *mut c_void, name: *const c_char, kind: c_int, duration_ns: u64) {
    let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        if ctx.is_null() || name.is_null() {
            return;
        }
        // SAFETY: `ctx` is the `&mut Vec<Event>` `stop` passed, alive for the whole call; `name`
        // is a NUL-terminated string the C++ side keeps alive for this call.
        #[allow(unsafe_code)]
        let (events, name) =
            unsafe { (&mut *ctx.cast::<Vec<Event>>(), CStr::from_ptr(name).to_string_lossy()) };
        events.push(Event {
            name: name.into_owned(),
            kind: EventKind::from_code(kind),
            duration_ns,
        });
    }));
}

impl Profiling {
    /// Stops the profiler; every event recorded since [`start`].
    pub fn stop(mut self) -> Result<Vec<Event>, ProfilerError> {
        self.stopped = true;
        stop_into()
    }
}

fn stop_into() -> Result<Vec<Event>, ProfilerError> {
    let mut events: Vec<Event> = Vec::new();
    let ctx = (&mut events as *mut Vec<Event>).cast::<c_void>();
    // SAFETY: `ctx` points at `events`, which outlives the call; `sink` matches the C signature and
    // never unwinds; the C++ function catches every exception and writes at most `len` bytes.
    #[allow(unsafe_code)]
    let stop = |err, len| unsafe { crate::ffi::pdt_profiler_stop(ctx, sink, err, len) };
    let rc = crate::ffi::call(stop);
    ACTIVE.store(false, Ordering::SeqCst);
    rc.map(|_| events).map_err(ProfilerError)
}

impl Drop for Profiling {
    fn drop(&mut self) {
        if !self.stopped {
            let _ = stop_into();
        }
    }
}
