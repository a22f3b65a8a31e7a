//! What the serve tests share: a tiny trained run, a server on loopback, one raw HTTP request.
#![allow(dead_code)] // each test file uses a part
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_serve::{ServeOptions, Server};
use pdt_train::config::TrainConfig;
use pdt_train::run::{train, ServedRun, TrainOptions};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::Duration;

/// A tiny trained point-robot Prompt-DT run, made once.
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
        let run = tmp.path().join("run");
        let mut progress = |_: &pdt_train::run::Progress| {};
        let opts = TrainOptions {
            resume: false,
            resume_with: Default::default(),
            stop_after_iterations: None,
            progress: &mut progress,
        };
        train(Some(c), &run, opts).unwrap();
        (tmp, run)
    })
}

pub fn start(opts: ServeOptions) -> Server {
    let run = ServedRun::load(&tiny_run().1, None, None).unwrap();
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
