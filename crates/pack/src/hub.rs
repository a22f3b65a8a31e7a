//! The meeting point of a pack's runs: each run's thread submits its gradient step, prepares its
//! next batch and waits; when every run still training has submitted (or left), one call of the
//! engine steps them all (by the pack's stepper thread, [`Hub::stepper`], or a waiting run if it
//! gets there first) and each run gets its own result.

use crate::engine::{PackEngine, SlotStep};
use pdt_train::optim::SlotState;
use pdt_train::run::RunError;
use pdt_train::step::PendingStats;
use pdt_train::streams::torch_rng_lock;
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
    results: Vec<Option<Result<PendingStats, String>>>,
    /// The pack's runs have all returned: [`Hub::stepper`] ends.
    closed: bool,
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
        let mut out = {
            let _rng = torch_rng_lock();
            // A panic in the engine (a libtorch error) fails this step for every run in it,
            // rather than leaving the others waiting for results that never come.
            let engine = &mut self.engine;
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| engine.step(steps)))
                .unwrap_or_else(|_| Err(RunError::Internal("the engine panicked".into())))
        };
        for i in (0..submitted.len()).filter(|&i| submitted[i]) {
            self.results[i] = Some(match &mut out {
                Ok(stats) => stats.get_mut(i).and_then(Option::take).ok_or_else(|| {
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
                results: (0..n).map(|_| None).collect(),
                closed: false,
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
    /// training has submitted, the stepper ([`Self::stepper`]) or a run waiting in [`Self::wait`]
    /// takes the engine step.
    pub(crate) fn submit(&self, slot: usize, step: SlotStep) -> Result<(), RunError> {
        let mut t = self.lock();
        if !t.active.get(slot).copied().unwrap_or(false) {
            return Err(RunError::Internal(format!("slot {slot} is not training in this pack")));
        }
        if t.pending[slot].is_some() || t.results[slot].is_some() {
            return Err(RunError::Internal(format!(
                "slot {slot} submitted a step before taking its last one's result"
            )));
        }
        t.pending[slot] = Some(step);
        if t.ready() {
            self.stepped.notify_all();
        }
        Ok(())
    }

    /// The result of `slot`'s submitted step, taking the engine step if the pack is ready and no
    /// other run has taken it yet. Returns once the step is taken; its statistics may still be
    /// computing (`PendingStats::read_all`).
    pub(crate) fn wait(&self, slot: usize) -> Result<PendingStats, RunError> {
        let mut t = self.lock();
        loop {
            if let Some(r) = t.results.get_mut(slot).and_then(Option::take) {
                return r.map_err(RunError::Internal);
            }
            if self.step_if_ready(&mut t) {
                continue;
            }
            if t.pending.get(slot).is_none_or(Option::is_none) {
                return Err(RunError::Internal(format!("slot {slot} waits for no submitted step")));
            }
            t = self.stepped.wait(t).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Takes each pack step as soon as every run still training has submitted, until [`Self::close`]
    /// (run on a thread of its own beside the runs'). Why: a run submits its step, then samples its
    /// next batch, then waits. Without this thread a step is taken by a run that waits, so once the
    /// last run submitted, the step started only when the first run had sampled its next batch
    /// (each run samples at once, after its own submission): the device idled for a sampling
    /// between steps. A run that waits still takes a ready step itself if it gets there first.
    pub(crate) fn stepper(&self) {
        let mut t = self.lock();
        loop {
            if t.closed {
                return;
            }
            if self.step_if_ready(&mut t) {
                continue;
            }
            t = self.stepped.wait(t).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Ends [`Self::stepper`] (every run of the pack has returned).
    pub(crate) fn close(&self) {
        self.lock().closed = true;
        self.stepped.notify_all();
    }

    /// `slot`'s run stops training (finished, stopped or failed): the others no longer wait for it.
    pub(crate) fn leave(&self, slot: usize) {
        let mut t = self.lock();
        if let Some(a) = t.active.get_mut(slot) {
            *a = false;
            t.pending[slot] = None;
        }
        self.step_if_ready(&mut t);
    }

    /// One engine step if every run still training has submitted (the runs waiting told): whether
    /// it took one.
    fn step_if_ready(&self, t: &mut Table) -> bool {
        if !t.ready() {
            return false;
        }
        t.step();
        self.stepped.notify_all();
        true
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

#[cfg(test)]
mod tests {
    //! The hub over the real batched engine: its stepper takes a ready step.
    #![allow(clippy::unwrap_used)] // a failed unwrap is a failed test

    use super::*;
    use crate::{BatchedEngine, PackLayout, SlotSpec};
    use pdt_model::{PromptDtConfig, Segments};
    use pdt_rundir::config::{AdamWConfig, LossOn};
    use pdt_train::step::PendingStats;
    use tch::Device;

    const K: usize = 3;

    fn cfg() -> PromptDtConfig {
        PromptDtConfig {
            hidden_size: 16,
            n_layer: 1,
            n_head: 2,
            n_inner: 32,
            max_ep_len: 30,
            n_positions: 3 * (2 + K),
            ..PromptDtConfig::reference(2, 2)
        }
    }

    fn engine() -> BatchedEngine {
        let specs = (0..3)
            .map(|seed| SlotSpec {
                model: cfg(),
                uses_prompt: false,
                loss_on: LossOn::History,
                optim: AdamWConfig::default(),
                last_block: pdt_rundir::config::LastBlockChoice::Auto,
                seed,
            })
            .collect();
        let layout = PackLayout { batch_size: 2, history_len: K, prompt_len: 0 };
        // Its initial weights come from libtorch's generator, which another test of this process
        // may be drawing from (a pack step's dropout): held, as the pack's own callers hold it.
        let _rng = torch_rng_lock();
        BatchedEngine::new(specs, layout, Device::Cpu).unwrap()
    }

    /// Run `slot`'s batch of 2 histories.
    fn history(slot: usize) -> Segments {
        let v: Vec<f32> = (0..2 * K * 2).map(|i| 0.01 * (i + 7 * slot) as f32).collect();
        let rtg = vec![0.5f32; 2 * K];
        let ts: Vec<i64> = (0..2 * K as i64).map(|i| i % K as i64).collect();
        let mask = vec![1f32; 2 * K];
        Segments::from_host(2, K, 2, 2, &v, &v, &rtg, &ts, &mask, Device::Cpu)
    }

    /// The batched engine, saying when it has taken a step.
    struct Signalling {
        inner: BatchedEngine,
        stepped: std::sync::mpsc::Sender<usize>,
    }

    impl PackEngine for Signalling {
        fn slots(&self) -> usize {
            self.inner.slots()
        }
        fn step(
            &mut self,
            s: Vec<Option<SlotStep>>,
        ) -> Result<Vec<Option<PendingStats>>, RunError> {
            let n = s.iter().flatten().count();
            let out = self.inner.step(s);
            let _ = self.stepped.send(n);
            out
        }
        fn export(&self, slot: usize) -> Result<SlotState, RunError> {
            self.inner.export(slot)
        }
        fn import(&mut self, slot: usize, state: SlotState) -> Result<(), RunError> {
            self.inner.import(slot, state)
        }
    }

    #[test]
    fn the_stepper_takes_a_ready_step_while_no_run_waits() {
        let (tx, rx) = std::sync::mpsc::channel();
        let hub = Hub::new(Box::new(Signalling { inner: engine(), stepped: tx }));
        std::thread::scope(|scope| {
            let stepper = scope.spawn(|| hub.stepper());
            for slot in 0..3 {
                let batch = pdt_train::step::DeviceBatch { history: history(slot), prompt: None };
                hub.submit(slot, SlotStep { step: 0, batch }).unwrap();
            }
            // No run has called `wait`: only the stepper can have taken the step (without it, this
            // would time out).
            let n = rx.recv_timeout(std::time::Duration::from_secs(120)).unwrap();
            assert_eq!(n, 3);
            for slot in 0..3 {
                assert!(hub.wait(slot).unwrap().read().unwrap().loss.is_finite());
            }
            hub.close();
            stepper.join().unwrap();
        });
    }
}
