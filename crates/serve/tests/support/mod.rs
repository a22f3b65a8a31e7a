//! What the serve tests share: a tiny point-robot run directory, a server on loopback, one raw
//! HTTP request.
#![allow(dead_code)] // each test file uses a part
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_policy::{Policy, RunData};
use pdt_rundir::config::TrainConfig;
use pdt_rundir::{Latest, RunDir};
use pdt_serve::{ServeOptions, Server};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::Duration;

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
            ..Default::default()
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

pub fn start(opts: ServeOptions) -> Server {
    let run = Policy::load(&tiny_run().1, None, None).unwrap();
    Server::start(run, ServeOptions { listen: SocketAddr::from(([127, 0, 0, 1], 0)), ..opts })
        .unwrap()
}

/// One HTTP/1.1 request; returns the status and the body as JSON (Null when empty).
pub fn http(
    addr: SocketAddr,
    method: &str,
    path: &str,
    body: Option<&str>,
) -> (u16, serde_json::Value) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let body = body.unwrap_or("");
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    let status: u16 = out.split(' ').nth(1).unwrap().parse().unwrap();
    let payload = out.split("\r\n\r\n").nth(1).unwrap_or("");
    (status, serde_json::from_str(payload).unwrap_or(serde_json::Value::Null))
}
