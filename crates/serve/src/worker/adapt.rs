//! Episodes that act after an evaluation-time adaptation (an opening request's `adapt`;
//! docs/serve.md, docs/prompt-control.md). One adaptation per task, seed, prompt strategy and
//! kind, made by `pdt_policy` (`pdt_eval::testtime`'s) when the first such episode opens (it takes
//! the model thread for the adaptation's time) and kept for the next ones, which then cost what
//! any episode costs. The request's settings become a [`TestTime`]; the library does the rest.

use super::{Episode, Worker};
use crate::{ApiError, OpenRequest, StatusCode};
use pdt_eval::testtime::TaskAdaptation;
use pdt_model::PrefixCache;
use pdt_policy::Policy;
use pdt_prompt::PromptStrategy;
use pdt_rundir::config::{Adaptation, TestTime};
use std::collections::{HashMap, HashSet};

/// Adaptations kept at most; one more evicts those no open episode acts with.
pub const MAX_ADAPTATIONS: usize = 64;

/// What names an adaptation: the same key, the same result (every draw is seeded by `seed`).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub(crate) struct AdaptKey {
    pub(crate) task: usize,
    pub(crate) seed: u64,
    /// The test time (its strategy and the adaptation's settings), written out (plain data).
    settings: String,
}

impl AdaptKey {
    pub(crate) fn new(task: usize, seed: u64, test_time: &TestTime) -> Self {
        Self { task, seed, settings: format!("{test_time:?}") }
    }
}

/// A kept adaptation and its prompt's keys and values (one row).
pub(crate) struct Kept {
    pub(crate) adaptation: TaskAdaptation,
    pub(crate) prefix: PrefixCache,
}

/// The server's adaptations.
#[derive(Default)]
pub(crate) struct Adaptations {
    kept: HashMap<AdaptKey, Kept>,
}

impl Adaptations {
    pub(crate) fn get(&self, key: &AdaptKey) -> Option<&Kept> {
        self.kept.get(key)
    }

    /// The adaptation of `key`, made now unless kept. `in_use`: the keys open episodes act
    /// with, never evicted.
    pub(crate) fn obtain(
        &mut self,
        run: &Policy,
        key: &AdaptKey,
        test_time: &TestTime,
        in_use: &HashSet<&AdaptKey>,
    ) -> Result<&Kept, ApiError> {
        if !self.kept.contains_key(key) {
            if self.kept.len() >= MAX_ADAPTATIONS {
                self.kept.retain(|k, _| in_use.contains(k));
            }
            if self.kept.len() >= MAX_ADAPTATIONS {
                return Err(ApiError::new(
                    StatusCode::TOO_MANY_REQUESTS,
                    format!(
                        "{MAX_ADAPTATIONS} adaptations are in use by open episodes, the limit; \
                         close some, or open episodes with an adaptation already made (same \
                         task, prompt_seed and settings)"
                    ),
                ));
            }
            let adaptation = run.adapt(key.task, key.seed, test_time)?;
            let prefix = adaptation.prefix(&run.model);
            self.kept.insert(key.clone(), Kept { adaptation, prefix });
        }
        self.kept.get(key).ok_or_else(|| ApiError::bad("adaptation vanished (internal error)"))
    }
}

impl Worker {
    /// The adaptation an opening request asks for (its own `adapt`, else the server's), from the
    /// prompt `strategy` picks, as a test time; `None` without one.
    pub(crate) fn adaptation(
        &self,
        req: &OpenRequest,
        strategy: &PromptStrategy,
    ) -> Result<Option<TestTime>, ApiError> {
        let mut cfg = self.opts.adapt.clone();
        if let Some(name) = &req.adapt {
            cfg.kind = name.parse().map_err(|e: pdt_rundir::config::AdaptError| {
                ApiError::bad(format!("adapt: {e}"))
            })?;
        }
        let adapt =
            |cfg| TestTime::Adapt { from: strategy.clone(), adaptation: Adaptation::Prompt(cfg) };
        match (cfg.is_none(), req.task, req.adapt.is_some()) {
            (true, ..) => Ok(None),
            (false, Some(_), _) => Ok(Some(adapt(cfg))),
            (false, None, true) => Err(ApiError::bad(
                "adapt learns from a `task`'s demonstrations: send a `task` (not `prompt`)",
            )),
            // The server's default adaptation applies to `task` episodes only.
            (false, None, false) => Ok(None),
        }
    }

    /// Opens an episode of `req.task` acting with the task's adaptation (made now unless kept).
    pub(crate) fn open_adapted(
        &mut self,
        req: OpenRequest,
        obs: pdt_policy::Observation,
        test_time: TestTime,
    ) -> Result<u64, ApiError> {
        let task = req.task.ok_or_else(|| ApiError::bad("adapt needs a `task`"))?;
        let key = AdaptKey::new(task, req.prompt_seed.unwrap_or(0), &test_time);
        let in_use: HashSet<&AdaptKey> =
            self.episodes.values().filter_map(|e| e.adapted.as_ref()).collect();
        let kept = self.adaptations.obtain(&self.run, &key, &test_time, &in_use)?;
        let prefix = PrefixCache::cat(&[&kept.prefix]);
        let adapt_log = Some(kept.adaptation.log.clone());
        let target = self.run.target(req.target_return)?;
        let e = self.run.start(obs, target);
        let ep = Episode { adapted: Some(key), adapt_log, ..Episode::new(e, prefix) };
        Ok(self.insert(ep))
    }
}
