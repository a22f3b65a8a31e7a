//! The trainable methods, each behind [`Learner`], and the registry that maps a configuration's
//! `run.method` to one. The loop (`run_loop`) and the final evaluation (`evaluate`) own everything
//! a run has whatever its method (cadence, logs, checkpoint commits, resume points, RNG restore,
//! progress); a learner owns its model, optimiser, sampling, evaluation and tensor files. Test time
//! (prompt strategies, `[eval.adapt]`) is `pdt_eval::testtime`'s, which a learner's `evaluate`
//! calls with its model; the adaptations of a learner's own weights are its own (`finetune`,
//! MT-BC-Finetune's; `macaw`).
//!
//! A new method: its module here, one line in [`learner`] (and in [`steppable`] if it packs), and
//! its section of the configuration (`docs/adding-a-method.md`).

mod finetune;
mod learner;
pub(crate) mod macaw;
pub(crate) mod prompt_dt;

pub use learner::{
    CheckpointFiles, Evaluation, IterationAt, IterationMetrics, Learner, SavedSteps, Steppable,
    TaskEval,
};
pub use prompt_dt::read_iteration;

use crate::error::RunError;
use crate::setup::Setup;
use pdt_rundir::config::Method;

/// The registry: the learner of the run's method, its model initialised from the run seed.
/// Call it with libtorch's generator held (`streams::torch_rng_lock`).
pub(crate) fn learner<'s>(setup: &'s Setup) -> Result<Box<dyn Learner + 's>, RunError> {
    Ok(match setup.cfg.run.method {
        m @ (Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune) => {
            Box::new(prompt_dt::PromptDtLearner::new(setup, prompt_dt::Variant::of(m))?)
        }
        Method::Macaw => Box::new(macaw::MacawLearner::new(setup)?),
    })
}

/// The registry's packable learners: the learner of the run's method as a [`Steppable`], its model
/// initialised from the run seed, for a method that `Method::packs`; any other is refused by name.
/// Call it with libtorch's generator held (`streams::torch_rng_lock`).
pub fn steppable<'s>(setup: &'s Setup) -> Result<Box<dyn Steppable + 's>, RunError> {
    let method = setup.cfg.run.method;
    let learner: Option<Box<dyn Steppable + 's>> = match method {
        m @ (Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune) => {
            Some(Box::new(prompt_dt::PromptDtLearner::new(setup, prompt_dt::Variant::of(m))?))
        }
        Method::Macaw => None,
    };
    learner.filter(|_| method.packs()).ok_or_else(|| cannot_pack(method))
}

/// The error of a method that cannot train in a pack, naming it.
pub fn cannot_pack(method: Method) -> RunError {
    RunError::invalid(
        format!("run.method = \"{}\"", method.name()),
        "cannot train in a pack: only a method whose learner gives the pack its gradient steps \
         can (docs/packs.md; MACAW trains alone); train it with `promptdt train --config`",
    )
}

#[cfg(test)]
mod tests {
    use super::learner;
    use crate::setup::Setup;
    use pdt_rundir::config::{Method, TrainConfig};

    /// The registry builds a learner for every method of `Method::ALL` (its `match` has no `_`
    /// arm, so a new variant does not compile without one), on a tiny point-robot dataset, and
    /// each learner names its loss column.
    #[test]
    fn the_registry_builds_every_method() {
        let tmp = tempfile::tempdir().unwrap();
        let data = tmp.path().join("data");
        let family = pdt_envs::collect_scripted::ScriptedFamily::named("point_robot").unwrap();
        let collect = pdt_envs::collect_scripted::CollectConfig {
            episodes_per_task: 2,
            prompt_episodes: 1,
            ..pdt_envs::collect_scripted::CollectConfig::for_family(family)
        };
        pdt_envs::collect_scripted::collect(&collect, &data, &mut |_, _| {}).unwrap();
        for m in Method::ALL {
            let mut cfg: TrainConfig = toml::from_str(
                "[sampler]\nk = 4\nbatch_size_per_task = 1\n[model]\nhidden_size = 16\n\
                 n_layer = 1\nn_inner = 32\n[run]\nthreads = 1\ndevice = \"cpu\"\n",
            )
            .unwrap();
            cfg.data.dir = data.clone();
            cfg.run.method = m;
            if let Some(s) = m.section() {
                assert_eq!(s, "macaw", "{m:?}: give its section a tiny setting here");
                cfg.macaw.width = 8;
            }
            let setup = Setup::new(cfg, std::path::Path::new("no-run-dir")).unwrap();
            let built = {
                let _torch = crate::streams::torch_rng_lock();
                learner(&setup).map(|l| l.loss_metric())
            };
            let loss = built.unwrap_or_else(|e| panic!("{}: {e}", m.name()));
            assert!(loss.starts_with("train/"), "{}: {loss}", m.name());
        }
    }
}
