//! The solo engine's worker threads on the CPU: one per slot for the pack's life, owning the slot
//! (its model and optimiser) and taking its jobs (a step with its dropout masks, an export, an
//! import) in order.
//!
//! Why threads that live as long as the pack rather than one per step: a thread's libtorch
//! intra-op count (OpenMP's) is set once, its OpenMP helper threads stay, and glibc's malloc keeps
//! each thread in its own arena, which the process keeps at the arena's peak
//! (`pdt_model::host_memory`): a fresh thread per step would pick up arenas of other threads (the
//! step threads' and OpenMP helpers' alike) until every one of them held a step's peak.

use super::Slot;
use crate::error::RunError;
use crate::pack::engine::{SlotState, SlotStep};
use crate::step::StepStats;
use pdt_model::dropout::{Dropout, DropoutMasks};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::thread::JoinHandle;

/// What a worker is asked to do with its slot.
pub(super) enum Job {
    /// One gradient step with these masks (drawn beforehand: the worker draws nothing).
    Step(SlotStep, DropoutMasks),
    /// A copy of the slot's weights and optimiser state.
    Export,
    Import(SlotState),
}

/// A worker's answer to a [`Job`], in the order of the jobs.
pub(super) enum Reply {
    Step(StepStats),
    State(SlotState),
    Imported,
    Failed(RunError),
}

/// One slot on its own thread.
pub(super) struct Worker {
    slot: usize,
    /// `None` once dropped (closing it ends the thread).
    jobs: Option<Sender<Job>>,
    replies: Receiver<Reply>,
    thread: Option<JoinHandle<()>>,
}

impl Worker {
    /// Starts slot `slot`'s thread with `intra_op` libtorch threads.
    pub(super) fn start(slot: usize, owned: Slot, intra_op: usize) -> Result<Self, RunError> {
        let (jobs, inbox) = channel::<Job>();
        let (outbox, replies) = channel::<Reply>();
        let intra_op = i32::try_from(intra_op).unwrap_or(i32::MAX);
        let thread = std::thread::Builder::new()
            .name(format!("pack-slot-{slot}"))
            .spawn(move || serve(owned, intra_op, slot, &inbox, &outbox))
            .map_err(|e| RunError::Invalid(format!("pack engine: slot {slot}'s thread: {e}")))?;
        Ok(Self { slot, jobs: Some(jobs), replies, thread: Some(thread) })
    }

    /// Hands the worker a job (its reply comes with [`Self::reply`]).
    pub(super) fn send(&self, job: Job) -> Result<(), RunError> {
        let sent = self.jobs.as_ref().map(|j| j.send(job).is_ok()).unwrap_or(false);
        if sent {
            Ok(())
        } else {
            Err(self.gone())
        }
    }

    /// The reply to the oldest job not yet answered.
    pub(super) fn reply(&self) -> Result<Reply, RunError> {
        self.replies.recv().map_err(|_| self.gone())
    }

    /// A job and its reply.
    pub(super) fn call(&self, job: Job) -> Result<Reply, RunError> {
        self.send(job)?;
        self.reply()
    }

    fn gone(&self) -> RunError {
        RunError::Invalid(format!("pack engine: slot {}'s thread has ended", self.slot))
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        // Closing the channel ends the worker's loop; a worker that panicked has ended already.
        self.jobs = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The worker's loop: its jobs in order until the engine drops it.
fn serve(mut slot: Slot, intra_op: i32, index: usize, inbox: &Receiver<Job>, out: &Sender<Reply>) {
    // libtorch's intra-op thread count is per OS thread (OpenMP's): set once for this thread (it
    // also sets the process default, which is the same count for every thread of the pack).
    tch::set_num_threads(intra_op);
    for job in inbox {
        // A libtorch error (a panic in tch) fails this job, not the thread: the run fails with it,
        // and the engine can still be dropped.
        let done = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match job {
            Job::Step(input, masks) => Reply::Step(slot.step(&input, Dropout::Given(&masks))),
            Job::Export => Reply::State(slot.state()),
            Job::Import(state) => match slot.import(index, state) {
                Ok(()) => Reply::Imported,
                Err(e) => Reply::Failed(e),
            },
        }));
        let reply = done.unwrap_or_else(|_| {
            Reply::Failed(RunError::Invalid(format!(
                "pack engine: slot {index}'s step panicked (see above)"
            )))
        });
        if out.send(reply).is_err() {
            return;
        }
    }
}
