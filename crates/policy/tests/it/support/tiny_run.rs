//! A tiny point-robot run directory for the tests of the crates that act through a policy
//! (pdt-policy's own, and pdt-serve's, which include this file): neither links the trainer.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_run::RunData;
use pdt_rundir::config::TrainConfig;
use pdt_rundir::{Latest, RunDir};
use std::path::PathBuf;
use std::sync::OnceLock;

/// A tiny point-robot Prompt-DT run directory, made once: real data (the scripted collection),
/// the configuration, statistics and checkpoint files a trained run has, with seeded initial
/// weights. The serve tests check serving (the evaluator's actions, batching, refusals), which
/// holds for any weights; pdt-serve does not link the trainer, so the run is written here as the
/// trainer writes one (`pdt-rundir`'s writers, `pdt_model::checkpoint::save`).
pub fn tiny_run() -> &'static (tempfile::TempDir, PathBuf) {
    static RUN: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    RUN.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let data = tmp.path().join("data");
        let collect = pdt_envs::collect_scripted::CollectConfig {
            episodes_per_task: 3,
            prompt_episodes: 2,
            ..pdt_envs::collect_scripted::CollectConfig::for_family(
                pdt_envs::collect_scripted::ScriptedFamily::named("point_robot").unwrap(),
            )
        };
        pdt_envs::collect_scripted::collect(&collect, &data, &mut |_, _| {}).unwrap();
        let mut c: TrainConfig = toml::from_str(
            "[sampler]\nk = 4\nbatch_size_per_task = 1\n[model]\nhidden_size = 16\nn_layer = 2\n\
             n_inner = 32\n[optim]\nlearning_rate = 1e-3\nwarmup_steps = 2\n[train]\niterations = 4\n\
             steps_per_iteration = 3\ntest_eval_interval = 4\ntrain_eval_interval = 0\n\
             save_interval = 4\n[eval]\nepisodes = 1\n[run]\nthreads = 1\ndevice = \"cpu\"\n",
        )
        .unwrap();
        c.data.dir = data;
        c.validate().unwrap();
        let family = pdt_envs::family(&c.env.name).unwrap();
        let run_data = RunData::load(&c, family.as_ref()).unwrap();
        let run = tmp.path().join("run");
        let dir = RunDir::at(&run);
        std::fs::create_dir_all(dir.checkpoints_dir()).unwrap();
        dir.write_config(&c).unwrap();
        dir.write_stats(&run_data.stats).unwrap();
        tch::manual_seed(7);
        let vs = tch::nn::VarStore::new(tch::Device::Cpu);
        let _model = pdt_model::PromptDt::new(&vs.root(), &run_data.model_cfg);
        let step = 12;
        let weights = dir.checkpoint_file(&Latest::model_name(step));
        pdt_model::checkpoint::save(&vs, &weights, &run_data.model_cfg).unwrap();
        let latest = Latest {
            step,
            iteration: 4,
            model: Latest::model_name(step),
            state: Latest::state_name(step),
            keep: true,
        };
        dir.write_latest(&latest).unwrap();
        (tmp, run)
    })
}
