//! The meeting point of a pack's runs: each run's thread submits its gradient step, prepares its
//! next batch and waits; when every run still training has submitted (or left), one call of the
//! engine, by a waiting run, steps them all and each run gets its own result. An engine whose slots
//! step alone (`PackEngine::steps_alone`: the solo engine on its threads) starts each run's step as
//! soon as it is submitted, and the run waits for its own result only: its runs are not in
//! lockstep, as separate processes would not be.

use super::engine::{PackEngine, PendingStep, SlotState, SlotStep};
use crate::error::RunError;
use crate::step::StepStats;
use crate::streams::torch_rng_lock;
use std::sync::{Condvar, Mutex, MutexGuard};

/// The engine and the runs' submissions, behind one lock.
struct Table {
    engine: Box<dyn PackEngine + Send>,
    /// The runs still training (a run that finished, stopped or failed has left).
    active: Vec<bool>,
    /// The steps submitted and not yet taken.
    pending: Vec<Option<SlotStep>>,
    /// Each submitted run's result, until it takes it (an engine error as its message, shared by
    /// every run of the failed step).
    results: Vec<Option<Result<StepStats, String>>>,
    /// An engine that steps its slots alone: each run's started step (or the error of its start),
    /// until the run waits for it.
    started: Vec<Option<Result<PendingStep, RunError>>>,
}

impl Table {
    /// Every run still training has submitted, and at least one has.
    fn ready(&self) -> bool {
        let submitted = self.pending.iter().any(Option::is_some);
        submitted && self.active.iter().zip(&self.pending).all(|(a, p)| !a || p.is_some())
    }

    /// One engine step for the submitted runs; their results filed.
    fn step(&mut self) {
        let steps: Vec<Option<SlotStep>> = self.pending.iter_mut().map(Option::take).collect();
        let submitted: Vec<bool> = steps.iter().map(Option::is_some).collect();
        // libtorch's generator (the dropout masks) is the process's: no other run may draw from
        // it while the engine does.
        let out = {
            let _rng = torch_rng_lock();
            // A panic in the engine (a libtorch error) fails this step for every run in it,
            // rather than leaving the others waiting for results that never come.
            let engine = &mut self.engine;
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| engine.step(steps)))
                .unwrap_or_else(|_| Err(RunError::Invalid("the engine panicked".into())))
        };
        for i in (0..submitted.len()).filter(|&i| submitted[i]) {
            self.results[i] = Some(match &out {
                Ok(stats) => stats.get(i).copied().flatten().ok_or_else(|| {
                    format!("the pack engine returned no result for the run in slot {i}")
                }),
                Err(e) => Err(format!("the pack engine failed: {e}")),
            });
        }
    }
}

/// Where a pack's runs meet to be stepped together.
pub(crate) struct Hub {
    table: Mutex<Table>,
    stepped: Condvar,
}

impl Hub {
    pub(crate) fn new(engine: Box<dyn PackEngine + Send>) -> Self {
        let n = engine.slots();
        Self {
            table: Mutex::new(Table {
                engine,
                active: vec![true; n],
                pending: (0..n).map(|_| None).collect(),
                results: vec![None; n],
                started: (0..n).map(|_| None).collect(),
            }),
            stepped: Condvar::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Table> {
        // A run that panicked while holding the lock left the table consistent (every change to
        // it is a single assignment), so the others go on.
        self.table.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Submits `slot`'s gradient step without waiting for it, so that the run can prepare its next
    /// batch while the pack is stepped; [`Self::wait`] takes the result. Once every run still
    /// training has submitted, a run waiting in [`Self::wait`] takes the engine step.
    pub(crate) fn submit(&self, slot: usize, step: SlotStep) -> Result<(), RunError> {
        let mut t = self.lock();
        if !t.active.get(slot).copied().unwrap_or(false) {
            return Err(RunError::Invalid(format!("slot {slot} is not training in this pack")));
        }
        if t.pending[slot].is_some() || t.results[slot].is_some() || t.started[slot].is_some() {
            return Err(RunError::Invalid(format!(
                "slot {slot} submitted a step before taking its last one's result"
            )));
        }
        if t.engine.steps_alone() {
            let started = {
                // The step's dropout masks are drawn as it starts.
                let _rng = torch_rng_lock();
                let engine = &mut t.engine;
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| engine.start(slot, step)))
                    .unwrap_or_else(|_| Err(RunError::Invalid("the engine panicked".into())))
            };
            t.started[slot] = Some(started);
            return Ok(());
        }
        t.pending[slot] = Some(step);
        if t.ready() {
            self.stepped.notify_all();
        }
        Ok(())
    }

    /// The result of `slot`'s submitted step, taking the engine step if the pack is ready and no
    /// other run has taken it yet.
    pub(crate) fn wait(&self, slot: usize) -> Result<StepStats, RunError> {
        let mut t = self.lock();
        if let Some(started) = t.started.get_mut(slot).and_then(Option::take) {
            // The others may start, export or import while this step computes.
            drop(t);
            return started
                .and_then(PendingStep::wait)
                .map_err(|e| RunError::Invalid(format!("the pack engine failed: {e}")));
        }
        loop {
            if let Some(r) = t.results.get_mut(slot).and_then(Option::take) {
                return r.map_err(RunError::Invalid);
            }
            if t.ready() {
                t.step();
                self.stepped.notify_all();
                continue;
            }
            if t.pending.get(slot).is_none_or(Option::is_none) {
                return Err(RunError::Invalid(format!("slot {slot} waits for no submitted step")));
            }
            t = self.stepped.wait(t).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// `slot`'s run stops training (finished, stopped or failed): the others no longer wait for it.
    pub(crate) fn leave(&self, slot: usize) {
        let mut t = self.lock();
        if let Some(a) = t.active.get_mut(slot) {
            *a = false;
            t.pending[slot] = None;
            t.started[slot] = None;
        }
        if t.ready() {
            t.step();
            self.stepped.notify_all();
        }
    }

    /// `slot`'s weights and optimiser state as a solo run holds them.
    pub(crate) fn export(&self, slot: usize) -> Result<SlotState, RunError> {
        self.lock().engine.export(slot)
    }

    /// Sets `slot`'s weights and optimiser state.
    pub(crate) fn import(&self, slot: usize, state: SlotState) -> Result<(), RunError> {
        self.lock().engine.import(slot, state)
    }
}
