//! `promptdt serve` as a user runs it, with the documented Python client (`examples/serve_client.py`,
//! standard library only) and curl-style raw requests.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

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
    // With a token, as a server beyond loopback needs: the client sends it from its file.
    let token = tmp.path().join("token");
    std::fs::write(&token, "0123456789abcdef0123456789abcdef\n").unwrap();
    let mut server = Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args(["serve", "--run", run.to_str().unwrap(), "--listen", "127.0.0.1:0"])
        .arg("--token-file")
        .arg(&token)
        .env_remove(TOKEN_ENV)
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(server.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let url =
        line.trim().strip_prefix("listening on ").unwrap_or_else(|| panic!("{line}")).to_string();
    let client = |with_token: bool| {
        let mut c = Command::new("python3");
        c.arg(repo("examples/serve_client.py")).args(["--url", &url, "--task", "34"]);
        c.env_remove(TOKEN_ENV);
        if with_token {
            c.arg("--token-file").arg(&token);
        }
        c.output().unwrap()
    };
    let (refused, out) = (client(false), client(true));
    let _ = server.kill();
    let _ = server.wait();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("401"), "{refused:?}");
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

// ------------------------------------------------------------------------------------------------
// Hostile input through the real binary
// ------------------------------------------------------------------------------------------------

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// One tiny trained run shared by the tests below (training it is the slow part).
fn trained_run() -> &'static PathBuf {
    static RUN: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &RUN.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let cfg = tiny_setup(tmp.path());
        let run = tmp.path().join("run");
        ok(&[
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--quiet",
        ]);
        (tmp, run)
    })
    .1
}

/// `promptdt serve` on a free loopback port, killed when dropped.
struct Served {
    child: std::process::Child,
    addr: SocketAddr,
}

impl Served {
    /// Starts `sh -c "<prefix> exec promptdt serve --run RUN --listen 127.0.0.1:0 <extra>"`.
    fn start(shell_prefix: &str, extra: &[&str]) -> Self {
        let mut cmd = format!(
            "{shell_prefix} exec '{}' serve --run '{}' --listen 127.0.0.1:0",
            env!("CARGO_BIN_EXE_promptdt"),
            trained_run().display()
        );
        for a in extra {
            cmd.push_str(&format!(" '{a}'"));
        }
        let mut child = Command::new("sh")
            .args(["-c", &cmd])
            .env_remove(TOKEN_ENV)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let addr = line
            .trim()
            .strip_prefix("listening on http://")
            .unwrap_or_else(|| panic!("no address in {line:?}"))
            .parse()
            .unwrap();
        Self { child, addr }
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 request on a new connection; the status (0 when the server closed the connection
/// without a reply) and the body. Gives up after `wait`.
fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    body: &str,
    wait: Duration,
) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(wait)).unwrap();
    let msg = format!(
        "{method} {path} HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    if s.write_all(msg.as_bytes()).is_err() {
        return (0, String::new());
    }
    let mut out = Vec::new();
    if let Err(e) = s.read_to_end(&mut out) {
        use std::io::ErrorKind::{TimedOut, WouldBlock};
        // A reset is an answer (the server closed the connection at once); silence is not.
        assert!(
            !matches!(e.kind(), TimedOut | WouldBlock),
            "{method} {path}: no reply within {wait:?}; got {:?}",
            String::from_utf8_lossy(&out)
        );
    }
    let out = String::from_utf8_lossy(&out).into_owned();
    let status = out.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    (status, out.split("\r\n\r\n").nth(1).unwrap_or("").to_string())
}

fn post(addr: SocketAddr, path: &str, body: &str) -> (u16, String) {
    request(addr, "POST", path, body, Duration::from_secs(30))
}

/// The action of a reply; `None` where a value is not a number (`null` is how JSON writes NaN).
fn action_of(body: &str) -> Option<Vec<f32>> {
    let rest = body.split("\"action\":[").nth(1)?;
    let list = rest.split(']').next()?;
    list.split(',').map(|x| x.trim().parse::<f32>().ok().filter(|v| v.is_finite())).collect()
}

#[test]
fn serve_refuses_values_whose_normalisation_overflows_and_keeps_the_episode() {
    let s = Served::start("", &[]);
    let a = s.addr;
    let prompt = |state: &str, rtg: &str| {
        format!(
            r#""prompt": {{"states": [[{state}, 0.0]], "actions": [[0.1, 0.1]], "returns_to_go": [{rtg}], "timesteps": [0]}}"#
        )
    };
    // Finite f32 values whose normalisation or scaling overflows: refused by name, never a null action.
    let opens = [
        (r#"{"task": 34, "observation": [3e38, 0.0]}"#.to_string(), "observation[0]"),
        (r#"{"task": 34, "observation": [-3e38, 3e38]}"#.to_string(), "observation[0]"),
        (
            format!(r#"{{{}, "observation": [0.0, 0.0]}}"#, prompt("3e38", "-1.0")),
            "prompt.states[0][0]",
        ),
        (
            format!(r#"{{{}, "observation": [0.0, 0.0]}}"#, prompt("0.1", "3e38")),
            "prompt.returns_to_go[0]",
        ),
        (
            r#"{"task": 34, "observation": [0.0, 0.0], "target_return": 1e30}"#.to_string(),
            "target_return",
        ),
        (r#"{"task": 34, "observation": [1e30, 0.0]}"#.to_string(), "observation[0]"),
    ];
    for (body, field) in &opens {
        let (status, reply) = post(a, "/v1/episodes", body);
        assert_eq!(status, 400, "{body}: {reply}");
        assert!(reply.contains(field), "{body}: the error should name {field}: {reply}");
    }
    // An episode survives a bad step: the step is refused and the next good one acts as usual.
    let (status, reply) = post(a, "/v1/episodes", r#"{"task": 34, "observation": [0.0, 0.0]}"#);
    assert_eq!(status, 201, "{reply}");
    assert!(action_of(&reply).is_some(), "{reply}");
    let id = reply.split("\"episode\":").nth(1).unwrap().split(',').next().unwrap().to_string();
    let step = format!("/v1/episodes/{id}/step");
    let bad_steps = [
        (r#"{"reward": -0.5, "observation": [3e38, 0.0]}"#, "observation[0]"),
        (r#"{"reward": -0.5, "observation": [0.0, 1e30]}"#, "observation[1]"),
        (r#"{"reward": -3e38, "observation": [0.0, 0.0]}"#, "1e30"),
        (r#"{"reward": 1e30, "observation": [0.0, 0.0]}"#, "reward"),
    ];
    for (i, (body, field)) in bad_steps.iter().enumerate() {
        let (status, reply) = post(a, &step, body);
        assert_eq!(status, 400, "{body}: {reply}");
        assert!(reply.contains(field), "{body}: the error should name {field}: {reply}");
        assert!(!reply.contains("not a finite reward"), "{body}: -3e38 is finite: {reply}");
        let (status, reply) = post(a, &step, r#"{"reward": -0.5, "observation": [0.1, 0.0]}"#);
        assert_eq!(status, 200, "{reply}");
        assert!(action_of(&reply).is_some(), "after {body}: {reply}");
        assert!(
            reply.contains(&format!("\"t\":{}", i + 1)),
            "refused steps are not counted: {reply}"
        );
    }
}

#[test]
fn serve_times_out_silent_connections_and_bounds_them() {
    let s = Served::start(
        "",
        &["--header-timeout-s", "2", "--body-timeout-s", "1", "--max-connections", "8"],
    );
    let a = s.addr;
    // Eight connections that never finish their headers hold every slot ...
    let mut silent: Vec<TcpStream> = (0..8)
        .map(|_| {
            let mut c = TcpStream::connect(a).unwrap();
            c.write_all(b"GET /v1/info HTTP/1.1\r\nHost: t\r\n").unwrap();
            c
        })
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    // ... so a ninth is answered 503 at once, not left waiting.
    let t0 = Instant::now();
    let (status, reply) = request(a, "GET", "/v1/info", "", Duration::from_secs(5));
    assert!(status == 503 || status == 0, "{status} {reply}");
    assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
    // After the header timeout the server has closed them (EOF or a reset, not silence), and
    // answers again.
    std::thread::sleep(Duration::from_millis(2000));
    for c in &mut silent {
        c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut buf = Vec::new();
        if let Err(e) = c.read_to_end(&mut buf) {
            use std::io::ErrorKind::{TimedOut, WouldBlock};
            assert!(
                !matches!(e.kind(), TimedOut | WouldBlock),
                "a silent connection is still open"
            );
        }
    }
    let (status, reply) = request(a, "GET", "/v1/info", "", Duration::from_secs(5));
    assert_eq!(status, 200, "{reply}");
    // A body declared larger than --max-body-bytes is refused before it is read ...
    let mut c = TcpStream::connect(a).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    c.write_all(b"POST /v1/episodes HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\nContent-Length: 1000000000000\r\n\r\n{").unwrap();
    let mut out = String::new();
    let _ = c.read_to_string(&mut out);
    assert!(out.starts_with("HTTP/1.1 413"), "{out}");
    assert!(out.contains("max-body-bytes"), "{out}");
    // ... and a body that stops coming is given up after the body timeout.
    let mut c = TcpStream::connect(a).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    c.write_all(b"POST /v1/episodes HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"task\"").unwrap();
    let mut out = String::new();
    let _ = c.read_to_string(&mut out);
    assert!(out.starts_with("HTTP/1.1 408"), "{out}");
    assert!(out.contains("body-timeout-s"), "{out}");
    let (status, reply) = request(a, "GET", "/v1/info", "", Duration::from_secs(5));
    assert_eq!(status, 200, "{reply}");
}

#[test]
fn serve_keeps_answering_when_connections_reach_the_descriptor_limit() {
    // 256 descriptors and 300 connections that never send a byte: with the default flags the
    // server refuses the connections beyond its limit at once and keeps answering.
    let s = Served::start("ulimit -n 256 &&", &[]);
    let a = s.addr;
    // A body declared at 10^12 bytes is refused at once, not waited for.
    let mut c = TcpStream::connect(a).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    c.write_all(b"POST /v1/episodes HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\nContent-Length: 1000000000000\r\n\r\n{")
        .unwrap();
    let mut out = String::new();
    let read = c.read_to_string(&mut out);
    assert!(out.starts_with("HTTP/1.1 413"), "{read:?} {out}");
    let silent: Vec<TcpStream> = (0..300).filter_map(|_| TcpStream::connect(a).ok()).collect();
    std::thread::sleep(Duration::from_millis(300));
    let (status, reply) = request(a, "GET", "/v1/info", "", Duration::from_secs(5));
    assert!(status == 503 || status == 200, "{status} {reply}");
    drop(silent);
    std::thread::sleep(Duration::from_millis(300));
    let (status, reply) = request(a, "GET", "/v1/info", "", Duration::from_secs(5));
    assert_eq!(status, 200, "{reply}");
}

#[test]
fn serve_refuses_zero_and_absurd_limits() {
    let run = trained_run().to_str().unwrap().to_string();
    for (flag, value) in [
        ("--idle-timeout-s", "0"),
        ("--batch-wait-ms", "18446744073709551615"),
        ("--header-timeout-s", "0"),
        ("--body-timeout-s", "0"),
        ("--max-connections", "0"),
    ] {
        // Spawned with a deadline: a server that accepts the value would run forever.
        let mut child = Command::new(env!("CARGO_BIN_EXE_promptdt"))
            .args(["serve", "--run", &run, "--listen", "127.0.0.1:0", flag, value])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let t0 = Instant::now();
        let status = loop {
            if let Some(st) = child.try_wait().unwrap() {
                break st;
            }
            if t0.elapsed() > Duration::from_secs(30) {
                let _ = child.kill();
                let _ = child.wait();
                panic!("serve accepted {flag} {value} (still running after 30 s)");
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        let mut stderr = String::new();
        child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
        assert!(!status.success(), "{flag} {value}");
        assert!(
            stderr.contains(flag) && stderr.contains("must be between"),
            "{flag} {value}: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "{stderr}");
    }
}

#[test]
fn serve_adapts_task_episodes_with_its_adapt_flags() {
    // `--adapt lora` with a budget: a `task` episode acts after the task's adaptation, whose log
    // comes back with the first action; a request may name another adaptation or none.
    let s = Served::start("", &["--adapt", "lora", "--adapt-steps", "2", "--adapt-batch", "4"]);
    let obs = "[0.0, 0.0]";
    let (status, reply) =
        post(s.addr, "/v1/episodes", &format!(r#"{{"task": 2, "observation": {obs}}}"#));
    assert_eq!(status, 201, "{reply}");
    let v: serde_json::Value = serde_json::from_str(&reply).unwrap();
    assert_eq!(v["adaptation"]["steps"], 2, "{reply}");
    assert!(v["adaptation"]["trainable"].as_u64().unwrap() > 0, "{reply}");
    assert!(action_of(&reply).is_some(), "{reply}");
    let body = format!(r#"{{"task": 2, "adapt": "soft-prompt", "observation": {obs}}}"#);
    let (status, reply) = post(s.addr, "/v1/episodes", &body);
    assert_eq!(status, 201, "{reply}");
    assert!(reply.contains("\"adaptation\""), "{reply}");
    let body = format!(r#"{{"task": 2, "adapt": "none", "observation": {obs}}}"#);
    let (status, reply) = post(s.addr, "/v1/episodes", &body);
    assert_eq!(status, 201, "{reply}");
    assert!(!reply.contains("\"adaptation\""), "{reply}");
    // A bad budget is refused at start, naming the setting.
    let out = Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args(["serve", "--run", trained_run().to_str().unwrap(), "--listen", "127.0.0.1:0"])
        .args(["--adapt", "lora", "--lora-rank", "0"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("eval.adapt.lora.rank = 0"), "{stderr}");
}

// ------------------------------------------------------------------------------------------------
// Authentication and settings refused at start. Addresses other than
// loopback are bound only as 0.0.0.0 on port 0 and reached through 127.0.0.1.
// ------------------------------------------------------------------------------------------------

const TOKEN_ENV: &str = "PROMPTDT_SERVE_TOKEN";

/// `promptdt serve ARGS` (with `env` set, PROMPTDT_SERVE_TOKEN removed unless `env` sets it) that
/// must exit: its stderr. Fails the test if it is still serving after 60 s or exits 0.
fn refused_at_start(args: &[&str], env: &[(&str, &str)]) -> String {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_promptdt"));
    cmd.arg("serve").args(args).env_remove(TOKEN_ENV);
    cmd.envs(env.iter().copied()).stdout(Stdio::null()).stderr(Stdio::piped());
    let mut child = cmd.spawn().unwrap();
    let t0 = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("serve {args:?} started (still running after 60 s)");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut stderr = String::new();
    child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
    assert!(!status.success(), "serve {args:?} exited 0: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    stderr
}

/// `promptdt serve --run RUN ARGS` serving: the child, its stdout's lines after the address, and
/// the address to reach it on (127.0.0.1 where it listens on 0.0.0.0).
struct Exposed {
    child: std::process::Child,
    addr: SocketAddr,
    stdout: std::io::BufReader<std::process::ChildStdout>,
}

impl Exposed {
    fn start(args: &[&str], env: &[(&str, &str)]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_promptdt"))
            .args(["serve", "--run", trained_run().to_str().unwrap()])
            .args(args)
            .env_remove(TOKEN_ENV)
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        let listening: SocketAddr = line
            .trim()
            .strip_prefix("listening on http://")
            .unwrap_or_else(|| panic!("no address in {line:?}"))
            .parse()
            .unwrap();
        let addr = SocketAddr::from(([127, 0, 0, 1], listening.port()));
        Self { child, addr, stdout }
    }

    /// Stops it; its stderr.
    fn stop(mut self) -> String {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let mut stderr = String::new();
        self.child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
        stderr
    }
}

/// One request with `Authorization: Bearer <token>` when given: the status and the raw reply.
fn authed(
    addr: SocketAddr,
    method: &str,
    path: &str,
    body: &str,
    token: Option<&str>,
) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
    let msg = format!(
        "{method} {path} HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\n{auth}\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(msg.as_bytes()).unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    let status = out.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    (status, out)
}

#[test]
fn serve_refuses_an_address_other_than_loopback_without_a_token_or_no_auth() {
    let run = trained_run().to_str().unwrap();
    let e = refused_at_start(&["--run", run, "--listen", "0.0.0.0:0"], &[]);
    for says in ["0.0.0.0:0", "without authentication", "--token-file", TOKEN_ENV, "--no-auth"] {
        assert!(e.contains(says), "the refusal should name {says}: {e}");
    }
    // A token that cannot be read, or is no token, is refused by its file or variable.
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("missing-token");
    let empty = tmp.path().join("empty-token");
    std::fs::write(&empty, "\n").unwrap();
    let short = tmp.path().join("short-token");
    std::fs::write(&short, "abc123\n").unwrap();
    for (file, says) in [(&missing, "No such file"), (&empty, "empty"), (&short, "too few")] {
        let f = file.to_str().unwrap();
        let e = refused_at_start(&["--run", run, "--listen", "0.0.0.0:0", "--token-file", f], &[]);
        assert!(e.contains(f) && e.contains(says), "{f}: {e}");
    }
    let e = refused_at_start(&["--run", run, "--listen", "127.0.0.1:0"], &[(TOKEN_ENV, "")]);
    assert!(e.contains(TOKEN_ENV) && e.contains("empty"), "{e}");
    // Contradictions are refused, not settled silently.
    let e = refused_at_start(
        &["--run", run, "--listen", "0.0.0.0:0", "--no-auth"],
        &[(TOKEN_ENV, "pdt-test-token-0123456789")],
    );
    assert!(e.contains("--no-auth") && e.contains(TOKEN_ENV), "{e}");
    let f = empty.to_str().unwrap();
    let e = refused_at_start(&["--run", run, "--token-file", f, "--no-auth"], &[]);
    assert!(e.contains("--token-file") && e.contains("--no-auth"), "{e}");
}

#[test]
fn serve_with_no_auth_on_all_addresses_warns_and_serves() {
    let s = Exposed::start(&["--listen", "0.0.0.0:0", "--no-auth"], &[]);
    let (status, reply) = authed(s.addr, "GET", "/v1/info", "", None);
    assert_eq!(status, 200, "{reply}");
    let stderr = s.stop();
    let warnings: Vec<&str> = stderr.lines().filter(|l| l.starts_with("warning:")).collect();
    assert_eq!(warnings.len(), 1, "{stderr}");
    assert!(warnings[0].contains("without authentication (--no-auth)"), "{stderr}");
    // On loopback, no token and no warning, as before.
    let s = Exposed::start(&["--listen", "127.0.0.1:0"], &[]);
    assert_eq!(authed(s.addr, "GET", "/v1/info", "", None).0, 200);
    let stderr = s.stop();
    assert!(!stderr.contains("warning"), "{stderr}");
}

#[test]
fn serve_with_a_token_answers_401_without_it_and_serves_with_it() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("token");
    let secret = "pdt-test-token-from-a-file-0123456789";
    std::fs::write(&file, format!("{secret}\n")).unwrap();
    let open = r#"{"task": 34, "observation": [0.0, 0.0]}"#;
    let check = |addr: SocketAddr, secret: &str| {
        let (s, reply) = authed(addr, "GET", "/v1/health", "", None);
        assert_eq!(s, 200, "the health check is open: {reply}");
        for token in [None, Some("pdt-test-token-but-not-the-right-one")] {
            for (method, path, body) in [("GET", "/v1/info", ""), ("POST", "/v1/episodes", open)] {
                let (s, reply) = authed(addr, method, path, body, token);
                assert_eq!(s, 401, "{method} {path} {token:?}: {reply}");
                let lower = reply.to_lowercase();
                assert!(lower.contains("www-authenticate: bearer"), "{reply}");
                assert!(reply.contains("{\"error\":"), "{reply}");
            }
        }
        let (s, reply) = authed(addr, "POST", "/v1/episodes", open, Some(secret));
        assert_eq!(s, 201, "{reply}");
        assert!(action_of(&reply).is_some(), "{reply}");
    };
    // From a file, on all addresses, and on loopback too (a token given is always required).
    let f = file.to_str().unwrap();
    for listen in ["0.0.0.0:0", "127.0.0.1:0"] {
        let s = Exposed::start(&["--listen", listen, "--token-file", f], &[]);
        check(s.addr, secret);
        let stderr = s.stop();
        assert!(!stderr.contains("warning"), "{stderr}");
    }
    // From the environment.
    let from_env = "pdt-test-token-from-the-environment-42";
    let s = Exposed::start(&["--listen", "0.0.0.0:0"], &[(TOKEN_ENV, from_env)]);
    check(s.addr, from_env);
    s.stop();
    // Generated: printed once, on the line after the address.
    let mut s = Exposed::start(&["--listen", "0.0.0.0:0", "--generate-token"], &[]);
    let mut line = String::new();
    s.stdout.read_line(&mut line).unwrap();
    let generated = line.trim().strip_prefix("token: ").unwrap_or_else(|| panic!("{line:?}"));
    assert_eq!(generated.len(), 64, "{generated}");
    check(s.addr, generated);
    let stderr = s.stop();
    assert!(!stderr.contains(generated), "the token is printed once, on stdout: {stderr}");
}

#[test]
fn serve_refuses_adaptation_settings_that_would_refuse_every_episode() {
    let run = trained_run().to_str().unwrap();
    let e = refused_at_start(
        &["--run", run, "--listen", "127.0.0.1:0", "--adapt", "ptdt", "--ptdt-score", "return"],
        &[],
    );
    assert!(e.contains("--ptdt-score return") && e.contains("action-loss"), "{e}");
    let e = refused_at_start(
        &[
            "--run",
            run,
            "--listen",
            "127.0.0.1:0",
            "--adapt",
            "lora",
            "--prompt-strategy",
            "bandit",
        ],
        &[],
    );
    assert!(e.contains("--adapt lora") && e.contains("--prompt-strategy bandit"), "{e}");
    // A run without prompts (MT-ORL) has nothing to adapt.
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let mt_orl = tmp.path().join("mt-orl");
    let (c, out) = (cfg.to_str().unwrap(), mt_orl.to_str().unwrap());
    ok(&["train", "--config", c, "--method", "mt-orl", "--out", out, "--quiet"]);
    let e = refused_at_start(&["--run", out, "--listen", "127.0.0.1:0", "--adapt", "lora"], &[]);
    assert!(e.contains("--adapt lora") && e.contains("mt-orl") && e.contains("no prompt"), "{e}");
    // Without --adapt it serves, as before.
    let mut child = Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args(["serve", "--run", out, "--listen", "127.0.0.1:0"])
        .env_remove(TOKEN_ENV)
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let _ = child.kill();
    let _ = child.wait();
    assert!(line.starts_with("listening on"), "{line}");
}
