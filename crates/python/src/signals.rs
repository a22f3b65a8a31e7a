//! Long calls that Ctrl-C stops, and their progress reported to a Python callable.
//!
//! A long call (train, collect) runs on a worker thread while the calling thread waits with the GIL
//! released, waking every [`POLL`] to run Python's signal handlers (`PyErr_CheckSignals` runs them
//! on the main thread only, which is why the work moves off it). A `KeyboardInterrupt` (or any
//! exception a handler raises) sets the call's [`StopFlag`]; the library stops at its next check
//! (between gradient steps, between episodes), leaving only whole files and committed
//! checkpoints, and the exception is raised once the worker has returned.
//!
//! Progress is reported to a Python callable ([`Progress`]) from the worker thread, where the
//! library reports it (training's iterations, an agent's collection), or from the waiting thread,
//! which reads a count the work keeps ([`interruptible_ticking`]: the episodes of an evaluation
//! or of a scripted collection, played on threads the library does not let report).

use pdt_base::stop::StopFlag;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::{Condvar, Mutex};
use std::time::Duration;

/// How often the waiting thread runs the signal handlers: a Ctrl-C is seen within this.
const POLL: Duration = Duration::from_millis(50);

/// The worker's stack: as large as a main thread's, since the work ran on one before.
const WORKER_STACK: usize = 8 << 20;

/// Runs `work(interrupt)` on a worker thread until it returns or a signal handler raises; see
/// the module docs. `interrupt` is also what a progress callback's error sets ([`Progress`]).
pub(crate) fn interruptible<T: Send>(
    py: Python<'_>,
    interrupt: &StopFlag,
    work: impl FnOnce() -> T + Send,
) -> PyResult<T> {
    interruptible_ticking(py, interrupt, || {}, work)
}

/// [`interruptible`], calling `tick` on the waiting thread every [`POLL`] and once when the work
/// has returned: for progress the work counts rather than reports (an evaluation's or a
/// collection's episodes, counted by the threads playing them).
pub(crate) fn interruptible_ticking<T: Send>(
    py: Python<'_>,
    interrupt: &StopFlag,
    mut tick: impl FnMut(),
    work: impl FnOnce() -> T + Send,
) -> PyResult<T> {
    let done = Done::default();
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("promptdt-call".into())
            .stack_size(WORKER_STACK)
            .spawn_scoped(scope, || {
                // Signals the waiting thread however the work ends (a panic included).
                let _finished = Finished(&done);
                work()
            })
            .map_err(|e| {
                crate::errors::StateError::new_err(format!("cannot start a thread: {e}"))
            })?;
        let mut raised = None;
        loop {
            if py.detach(|| done.wait(POLL)) {
                tick();
                break;
            }
            tick();
            if raised.is_none() {
                if let Err(e) = py.check_signals() {
                    interrupt.set();
                    raised = Some(e);
                }
            }
        }
        // A panic in the work is re-raised here, where PyO3 turns it into a PanicException.
        let out = py.detach(|| worker.join()).unwrap_or_else(|p| std::panic::resume_unwind(p));
        match raised {
            Some(e) => Err(e),
            None => Ok(out),
        }
    })
}

/// Whether the worker has finished, and the condition the waiting thread sleeps on.
#[derive(Default)]
struct Done {
    finished: Mutex<bool>,
    changed: Condvar,
}

impl Done {
    /// Waits up to `timeout` for the worker; returns whether it has finished.
    fn wait(&self, timeout: Duration) -> bool {
        // A poisoned lock only means the worker panicked while setting it: it has finished.
        let Ok(guard) = self.finished.lock() else { return true };
        match self.changed.wait_timeout_while(guard, timeout, |finished| !*finished) {
            Ok((finished, _)) => *finished,
            Err(_) => true,
        }
    }
}

/// Marks [`Done`] when dropped, at the end of the worker.
struct Finished<'a>(&'a Done);

impl Drop for Finished<'_> {
    fn drop(&mut self) {
        if let Ok(mut finished) = self.0.finished.lock() {
            *finished = true;
        }
        self.0.changed.notify_all();
    }
}

/// A Python progress callable, called with one dict per report from the worker thread (taking
/// the GIL for the call). Its first exception stops the call ([`Progress::interrupt`]) and is the
/// one the call raises ([`Progress::take_error`]).
pub(crate) struct Progress {
    callback: Option<Py<PyAny>>,
    interrupt: StopFlag,
    error: Mutex<Option<PyErr>>,
}

impl Progress {
    pub(crate) fn new(callback: Option<Py<PyAny>>, interrupt: &StopFlag) -> Self {
        Self { callback, interrupt: interrupt.clone(), error: Mutex::new(None) }
    }

    /// Reports `fill`'s items to the callable, if there is one and it has not failed yet.
    pub(crate) fn report(&self, fill: impl FnOnce(&Bound<'_, PyDict>) -> PyResult<()>) {
        let Some(callback) = &self.callback else { return };
        if self.interrupt.is_set() {
            return;
        }
        let result = Python::attach(|py| {
            let d = PyDict::new(py);
            fill(&d)?;
            callback.call1(py, (d,)).map(drop)
        });
        if let Err(e) = result {
            if let Ok(mut slot) = self.error.lock() {
                slot.get_or_insert(e);
            }
            self.interrupt.set();
        }
    }

    /// The callable's exception, if it raised one.
    pub(crate) fn take_error(&self) -> Option<PyErr> {
        self.error.lock().ok().and_then(|mut e| e.take())
    }
}
