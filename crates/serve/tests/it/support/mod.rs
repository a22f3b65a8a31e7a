//! What the serve tests share: a tiny point-robot run directory, a server on loopback, one raw
//! HTTP request.
#![allow(dead_code)] // each test file uses a part
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_policy::Policy;
use pdt_serve::{ServeOptions, Server};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

// The run directory pdt-policy's tests act on (one file, shared by path: no crate of test
// helpers links the policy).
#[path = "../../../../policy/tests/it/support/tiny_run.rs"]
mod tiny;
pub use tiny::tiny_run;

/// One point-robot episode of `task` from `seed` with `prompt`, as the evaluator takes it.
pub fn point_task(
    task: usize,
    seed: u64,
    prompt: Option<pdt_prompt::SegmentBatch>,
) -> pdt_eval::EvalTask {
    pdt_eval::EvalTask {
        name: format!("point_robot-{task}"),
        index: task,
        envs: vec![pdt_envs::family("point_robot").unwrap().make(task).unwrap()],
        seeds: vec![seed],
        prompt,
        target_return: None,
    }
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
    let (status, _, body) = http_with(addr, method, path, body, &[]);
    (status, body)
}

/// [`http`] with extra header lines (`"Authorization: Bearer x"`); also returns the reply's
/// headers, lower-cased.
pub fn http_with(
    addr: SocketAddr,
    method: &str,
    path: &str,
    body: Option<&str>,
    headers: &[&str],
) -> (u16, String, serde_json::Value) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let body = body.unwrap_or("");
    let extra: String = headers.iter().map(|h| format!("{h}\r\n")).collect();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\n{extra}Connection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    let status: u16 = out.split(' ').nth(1).unwrap().parse().unwrap();
    let head = out.split("\r\n\r\n").next().unwrap_or("").to_lowercase();
    let payload = out.split("\r\n\r\n").nth(1).unwrap_or("");
    (status, head, serde_json::from_str(payload).unwrap_or(serde_json::Value::Null))
}
