//! The solo engine's worker threads on the CPU: one per slot for the pack's life, owning the slot
//! (its model and optimiser) and taking its jobs (a step with its dropout masks, an export, an
//! import) in order, each answered on the job's own channel (so a step's result can be awaited by
//! whoever started it, while others talk to the engine).
//!
//! Why threads that live as long as the pack rather than one per step: a thread's libtorch
//! intra-op count (OpenMP's) is set once, its OpenMP helper threads stay, and glibc's malloc keeps
//! each thread in its own arena, which the process keeps at the arena's peak
//! (`pdt_model::host_memory`): a fresh thread per step would pick up arenas of other threads (the
//! step threads' and OpenMP helpers' alike) until every one of them held a step's peak.

use super::Slot;
use crate::error::RunError;
use crate::pack::engine::{PendingStep, SlotState, SlotStep};
use crate::step::{unreadable, StepStats};
use pdt_model::dropout::{Dropout, DropoutMasks};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::thread::JoinHandle;

/// What a worker is asked to do with its slot.
enum Job {
    /// One gradient step with these masks (drawn beforehand: the worker draws nothing).
    Step(SlotStep, DropoutMasks),
    /// A copy of the slot's weights and optimiser state.
    Export,
    Import(SlotState),
}

/// A worker's answer to a [`Job`].
enum Reply {
    Step(StepStats),
    State(SlotState),
    Imported,
    Failed(RunError),
}

/// One slot on its own thread.
pub(super) struct Worker {
    slot: usize,
    /// Each job with the channel its reply goes to; `None` once dropped (closing it ends the
    /// thread).
    jobs: Option<Sender<(Job, Sender<Reply>)>>,
    thread: Option<JoinHandle<()>>,
}

impl Worker {
    /// Starts slot `slot`'s thread with `intra_op` libtorch threads.
    pub(super) fn start(slot: usize, owned: Slot, intra_op: usize) -> Result<Self, RunError> {
        let (jobs, inbox) = channel::<(Job, Sender<Reply>)>();
        let intra_op = i32::try_from(intra_op).unwrap_or(i32::MAX);
        let thread = std::thread::Builder::new()
            .name(format!("pack-slot-{slot}"))
            .spawn(move || serve(owned, intra_op, slot, &inbox))
            .map_err(|e| RunError::Invalid(format!("pack engine: slot {slot}'s thread: {e}")))?;
        Ok(Self { slot, jobs: Some(jobs), thread: Some(thread) })
    }

    /// Hands the worker a job; its reply comes on the returned channel.
    fn send(&self, job: Job) -> Result<Receiver<Reply>, RunError> {
        let (reply, answer) = channel();
        let sent = self.jobs.as_ref().is_some_and(|j| j.send((job, reply)).is_ok());
        if sent {
            Ok(answer)
        } else {
            Err(gone(self.slot))
        }
    }

    /// Starts a step with these masks; its statistics come with [`PendingStep::wait`].
    pub(super) fn step(
        &self,
        input: SlotStep,
        masks: DropoutMasks,
    ) -> Result<PendingStep, RunError> {
        let answer = self.send(Job::Step(input, masks))?;
        let slot = self.slot;
        Ok(PendingStep::new(move || match answer.recv().map_err(|_| gone(slot))? {
            Reply::Step(st) => Ok(st),
            Reply::Failed(e) => Err(e),
            _ => Err(unexpected(slot, "a step")),
        }))
    }

    /// A copy of the slot's weights and optimiser state.
    pub(super) fn export(&self) -> Result<SlotState, RunError> {
        match self.send(Job::Export)?.recv().map_err(|_| gone(self.slot))? {
            Reply::State(state) => Ok(state),
            Reply::Failed(e) => Err(e),
            _ => Err(unexpected(self.slot, "its state")),
        }
    }

    /// Sets the slot's weights and optimiser state.
    pub(super) fn import(&self, state: SlotState) -> Result<(), RunError> {
        match self.send(Job::Import(state))?.recv().map_err(|_| gone(self.slot))? {
            Reply::Imported => Ok(()),
            Reply::Failed(e) => Err(e),
            _ => Err(unexpected(self.slot, "an import")),
        }
    }
}

fn gone(slot: usize) -> RunError {
    RunError::Invalid(format!("pack engine: slot {slot}'s thread has ended"))
}

/// A worker's reply that should have been `what`.
fn unexpected(slot: usize, what: &str) -> RunError {
    RunError::Invalid(format!("pack engine: slot {slot}'s thread answered other than {what}"))
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
fn serve(mut slot: Slot, intra_op: i32, index: usize, inbox: &Receiver<(Job, Sender<Reply>)>) {
    // libtorch's intra-op thread count is per OS thread (OpenMP's): set once for this thread (it
    // also sets the process default, which is the same count for every thread of the pack).
    tch::set_num_threads(intra_op);
    for (job, out) in inbox {
        // A libtorch error (a panic in tch) fails this job, not the thread: the run fails with it,
        // and the engine can still be dropped.
        let done = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match job {
            // Read here: the worker's CPU step is done when it returns (nothing to wait for).
            Job::Step(input, masks) => match slot.step(&input, Dropout::Given(&masks)).read() {
                Ok(st) => Reply::Step(st),
                Err(e) => Reply::Failed(unreadable(e)),
            },
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
        // Nobody waiting (the caller gave up) is no reason to stop serving the others.
        let _ = out.send(reply);
    }
}
