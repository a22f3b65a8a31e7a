//! A run's set-up: the configuration checked against its environment and data, the data loaded
//! and checked by `pdt_run::RunData` (the loader a served policy draws its prompts with, so that
//! training, evaluation and serving see the same data), and the device.

use crate::error::RunError;
use crate::run_dir::EvalSchedule;
use pdt_data::MultiTaskDataset;
use pdt_envs::{EnvFamily, EnvPreset};
use pdt_eval::EvalReturns;
use pdt_prompt::BatchSampler;
use pdt_run::RunData;
use pdt_rundir::config::{Method, TrainConfig};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tch::Device;

/// Which tasks an evaluation covers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    Test,
    Train,
}

/// Everything built from the configuration and the data.
pub struct Setup {
    pub cfg: TrainConfig,
    pub(crate) family: Box<dyn EnvFamily>,
    pub(crate) preset: EnvPreset,
    /// The datasets, normalisation, sampler settings, model shape and the statistics the run
    /// records (`task_stats.json`). Shared by the runs of a pack with the same data settings
    /// (`pdt-pack`), so a pack holds one copy of them.
    pub(crate) run_data: Arc<RunData>,
    pub(crate) device: Device,
    /// Threads stepping the evaluation's environments: `eval.env_threads` resolved (0: all cores;
    /// in a pack, the run's share of them, [`Setup::with_data`]).
    pub(crate) env_threads: usize,
    /// Whether the evaluations play in a caller's environments ([`Setup::use_envs`], e.g.
    /// `promptdt.train(..., env=factory)`) in place of the family's own.
    pub(crate) caller_envs: bool,
}

/// `eval.env_threads` for one run of a pack of `pack_size` on `cores` cores: a set count as given;
/// 0 (all cores) the run's share, rounded up ([`Setup::with_data`]).
fn env_threads_in_pack(setting: usize, cores: usize, pack_size: usize) -> usize {
    match setting {
        0 => cores.max(1).div_ceil(pack_size.max(1)),
        n => n,
    }
}

impl Setup {
    /// The evaluation stream of `split` at `counter` (the iteration; a final evaluation counts
    /// down from `u64::MAX`, apart from training's).
    pub(crate) fn eval_rng(&self, split: Split, counter: u64) -> pdt_prompt::Rng {
        use pdt_run::streams::{STREAM_EVAL_TEST, STREAM_EVAL_TRAIN};
        use rand::SeedableRng;
        let stream = match split {
            Split::Test => STREAM_EVAL_TEST,
            Split::Train => STREAM_EVAL_TRAIN,
        };
        pdt_prompt::Rng::seed_from_u64(pdt_base::seed::derive_seed(
            self.cfg.run.seed,
            stream,
            counter,
        ))
    }

    /// The set-up of `cfg` for the run in `dir` (its environment family as the run trained on
    /// it: a task suite from the run's copy, [`pdt_envs::family_of_run`]).
    pub(crate) fn new(cfg: TrainConfig, dir: &Path) -> Result<Self, RunError> {
        cfg.validate()?;
        let copy = pdt_rundir::RunDir::at(dir).suite_path();
        let family = pdt_envs::family_of_run(&cfg.env.name, &copy)?;
        let preset = family.preset();
        let run_data = Arc::new(RunData::load(&cfg, family.as_ref())?);
        let device = pdt_torch::device::resolve(cfg.run.device)?;
        let env_threads = pdt_base::threads(cfg.eval.env_threads);
        Ok(Self { cfg, family, preset, run_data, device, env_threads, caller_envs: false })
    }

    /// The set-up of `cfg` over data already loaded for it, as one of `pack_size` runs in a process
    /// (a pack's runs with the same data settings: [`Setup::data_key`]). `eval.env_threads = 0`
    /// (all cores) gives each run its share of the cores, rounded up: the runs of a pack evaluate
    /// at the same iterations, and N runs each stepping its episodes on every core start N times
    /// the threads there are cores for, each with a few environments' work per step (results do
    /// not depend on the count).
    pub fn with_data(
        cfg: TrainConfig,
        run_data: Arc<RunData>,
        pack_size: usize,
    ) -> Result<Self, RunError> {
        cfg.validate()?;
        let family = pdt_envs::family(&cfg.env.name)?;
        let preset = family.preset();
        let device = pdt_torch::device::resolve(cfg.run.device)?;
        let cores = pdt_base::threads::available_cores();
        let env_threads = env_threads_in_pack(cfg.eval.env_threads, cores, pack_size);
        Ok(Self { cfg, family, preset, run_data, device, env_threads, caller_envs: false })
    }

    /// What `RunData::load` reads of `cfg`, as text: two configurations with the same key load
    /// the same data. The settings it never reads (seed, training cadence, optimiser) are blanked,
    /// and the method is reduced to what the loader asks of it (whether history returns are
    /// zeroed); everything else counts, so a setting the loader may read one day never makes two
    /// runs share data they would load differently.
    pub fn data_key(cfg: &TrainConfig) -> Result<String, RunError> {
        let mut k = cfg.clone();
        k.run.seed = 0;
        k.train = Default::default();
        k.optim = Default::default();
        k.run.method = if cfg.run.method.zeroes_history_returns() {
            Method::PromptMtBc
        } else {
            Method::PromptDt
        };
        Ok(k.to_toml()?)
    }

    pub(crate) fn sampler<'a>(
        &self,
        data: &'a MultiTaskDataset,
    ) -> Result<BatchSampler<'a>, RunError> {
        Ok(self.run_data.sampler(data)?)
    }

    pub(crate) fn eval_returns(&self) -> EvalReturns {
        pdt_run::eval_returns(&self.cfg)
    }

    /// The tasks of `split` and their data.
    pub(crate) fn data(&self, split: Split) -> &MultiTaskDataset {
        match split {
            Split::Test => &self.run_data.test_data,
            Split::Train => &self.run_data.train_data,
        }
    }

    /// Why the run's periodic evaluation in its environment is skipped, if it is: a task suite
    /// that declares no environment has none to act in (docs/your-own-tasks.md), unless a
    /// caller gave its environments ([`Setup::use_envs`]).
    pub fn online_evaluation_note(&self) -> Option<String> {
        if self.caller_envs {
            return None;
        }
        let suite = self.family.as_suite()?;
        suite.environment().is_none().then(|| {
            format!(
                "{} declares no [environment]: no evaluation in an environment during training \
                 (the suite's tasks have data only); the prompted model's action error on the \
                 held-out tasks' data is recorded instead, in offline_eval.jsonl (not for MACAW)",
                suite.path().display()
            )
        })
    }

    /// The G* task `index` (the family's) is evaluated with: the run's `eval.target_return` when
    /// set, else the task's own (a suite's `[[tasks]] target_return`), else the run's
    /// (`task_stats.json`'s). What `pdt_eval::testtime::SplitEval::task_target_return` conditions
    /// the task's episodes on, and what its `eval.jsonl` lines record.
    pub fn task_target_return(&self, index: usize) -> f32 {
        let own =
            self.family.task_target_return(index).filter(|_| self.cfg.eval.target_return.is_none());
        own.unwrap_or(self.run_data.stats.target_return)
    }

    /// Whether the run evaluates offline (`pdt_eval::offline`, the action error on the held-out
    /// tasks' data) in place of episodes in an environment: a suite with no environment.
    pub fn evaluates_offline(&self) -> bool {
        self.online_evaluation_note().is_some()
    }

    /// How many evaluation lines the run's logs hold at least, per iteration done.
    pub(crate) fn eval_schedule(&self) -> EvalSchedule {
        // A run with no environment to evaluate in logs no evaluation lines.
        let evaluates = usize::from(self.online_evaluation_note().is_none());
        EvalSchedule {
            test_tasks: self.run_data.test_data.tasks.len() * evaluates,
            train_tasks: self.run_data.train_data.tasks.len() * evaluates,
            test_eval_interval: self.cfg.train.test_eval_interval,
            train_eval_interval: self.cfg.train.train_eval_interval,
        }
    }
}

/// `path` made absolute against the current directory (not resolving symlinks; the path need
/// not exist yet).
pub fn absolute(path: &Path) -> PathBuf {
    std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pack's runs share their loaded data exactly when the loader would read the same.
    #[test]
    fn data_key_ignores_what_the_loader_never_reads() {
        let base = TrainConfig::default();
        let key = |f: &dyn Fn(&mut TrainConfig)| {
            let mut c = base.clone();
            f(&mut c);
            Setup::data_key(&c).ok()
        };
        let same = key(&|_| {});
        assert!(same.is_some());
        for change in [
            &|c: &mut TrainConfig| c.run.seed = 7,
            &|c: &mut TrainConfig| c.run.method = Method::MtOrl,
            &|c: &mut TrainConfig| c.train.iterations = 3,
            &|c: &mut TrainConfig| c.optim.learning_rate = 0.5,
        ] as [&dyn Fn(&mut TrainConfig); 4]
        {
            assert_eq!(key(change), same);
        }
        for change in [
            &|c: &mut TrainConfig| c.run.method = Method::PromptMtBc,
            &|c: &mut TrainConfig| c.sampler.prompt_length = Some(1),
            &|c: &mut TrainConfig| c.data.dir = "elsewhere".into(),
            &|c: &mut TrainConfig| c.model.hidden_size = 8,
        ] as [&dyn Fn(&mut TrainConfig); 4]
        {
            assert_ne!(key(change), same);
        }
    }

    /// "All cores" in a pack is each run's share of them, never less than one thread.
    #[test]
    fn a_packs_runs_share_the_cores_for_their_environments() {
        assert_eq!(env_threads_in_pack(0, 16, 1), 16, "a run alone: every core");
        assert_eq!(env_threads_in_pack(0, 16, 12), 2, "16 cores, 12 runs: 2 each (rounded up)");
        assert_eq!(env_threads_in_pack(0, 16, 36), 1);
        assert_eq!(env_threads_in_pack(0, 2, 3), 1);
        assert_eq!(env_threads_in_pack(0, 0, 0), 1, "nothing known: one thread");
        assert_eq!(env_threads_in_pack(5, 16, 12), 5, "a set count is kept");
    }
}
