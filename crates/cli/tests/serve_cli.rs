//! `promptdt serve` as a user runs it, with the documented Python client (`examples/serve_client.py`,
//! standard library only) and curl-style raw requests.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

#[path = "support/cli.rs"]
mod cli;

use cli::{ok, repo, tiny_setup};
use std::io::BufRead;
use std::process::{Command, Stdio};

#[test]
fn the_python_client_example_runs_against_promptdt_serve() {
    if Command::new("python3").arg("--version").output().is_err() {
        return eprintln!("skipped: no python3");
    }
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("run");
    ok(&["train", "--config", cfg.to_str().unwrap(), "--out", run.to_str().unwrap(), "--quiet"]);
    let mut server = Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args(["serve", "--run", run.to_str().unwrap(), "--listen", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(server.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let url =
        line.trim().strip_prefix("listening on ").unwrap_or_else(|| panic!("{line}")).to_string();
    let out = Command::new("python3")
        .arg(repo("examples/serve_client.py"))
        .args(["--url", &url, "--task", "34"])
        .output()
        .unwrap();
    let _ = server.kill();
    let _ = server.wait();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("serving prompt-dt") && stdout.contains("episode return"), "{stdout}");
}

#[test]
fn serve_refuses_a_directory_that_is_not_a_run() {
    let tmp = tempfile::tempdir().unwrap();
    let e =
        cli::fails(&["serve", "--run", tmp.path().to_str().unwrap(), "--listen", "127.0.0.1:0"]);
    assert!(e.contains("not a run directory"), "{e}");
}
