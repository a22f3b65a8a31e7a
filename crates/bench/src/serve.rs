//! `serve_c<N>`: latency and throughput of `promptdt serve` with N concurrent episodes on loopback.
//! N client threads, each with a kept-alive HTTP/1.1 connection, run episodes of `steps` steps
//! (random observations of the run's size; the latency does not depend on their values); every
//! request's round trip is timed.

use crate::{percentile, BenchError};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::{Duration, Instant};

/// Round trips of one case, in milliseconds, and the actions per second over the whole run.
pub struct ServeTiming {
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub actions_per_s: f64,
    pub requests: usize,
}

/// A kept-alive connection.
struct Conn {
    w: TcpStream,
    r: BufReader<TcpStream>,
}

impl Conn {
    fn new(addr: SocketAddr) -> std::io::Result<Self> {
        let w = TcpStream::connect(addr)?;
        w.set_nodelay(true)?;
        w.set_read_timeout(Some(Duration::from_secs(60)))?;
        Ok(Self { r: BufReader::new(w.try_clone()?), w })
    }

    /// One request; returns the body (status must be 2xx).
    fn call(&mut self, method: &str, path: &str, body: &str) -> std::io::Result<String> {
        write!(
            self.w,
            "{method} {path} HTTP/1.1\r\nHost: b\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        )?;
        let mut line = String::new();
        self.r.read_line(&mut line)?;
        let ok = line.split(' ').nth(1).is_some_and(|s| s.starts_with('2'));
        let mut len = 0usize;
        loop {
            line.clear();
            self.r.read_line(&mut line)?;
            let l = line.trim_end();
            if l.is_empty() {
                break;
            }
            if let Some(v) = l.to_ascii_lowercase().strip_prefix("content-length:") {
                len = v.trim().parse().unwrap_or(0);
            }
        }
        let mut buf = vec![0u8; len];
        self.r.read_exact(&mut buf)?;
        let text = String::from_utf8_lossy(&buf).into_owned();
        if ok {
            Ok(text)
        } else {
            Err(std::io::Error::other(text))
        }
    }
}

/// Serves the run in `run` in this process and drives `clients` episodes at once.
pub fn time_serve(
    run: &Path,
    clients: usize,
    steps: usize,
    episodes_per_client: usize,
) -> Result<ServeTiming, BenchError> {
    let err = |why: String| BenchError::Baseline { cmd: format!("serve_c{clients}"), why };
    let served = pdt_policy::Policy::load(run, None, None).map_err(|e| err(e.to_string()))?;
    let (ds, uses_prompt) = (served.stats.obs_dim, served.method.uses_prompt());
    let task = served.prompt_tasks().ok().and_then(|t| t.first().copied());
    let opts = pdt_serve::ServeOptions {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        max_batch: clients.max(1),
        batch_wait: Duration::from_micros(500),
        threads: 1,
        ..Default::default()
    };
    let mut server = pdt_serve::Server::start(served, opts).map_err(|e| err(e.to_string()))?;
    let addr = server.addr;
    let obs = |t: usize| -> String {
        let v: Vec<String> =
            (0..ds).map(|j| format!("{:.4}", ((t * 7 + j) as f64).sin() * 0.1)).collect();
        format!("[{}]", v.join(","))
    };
    let open_body = move |t: usize| match (uses_prompt, task) {
        (true, Some(k)) => format!("{{\"task\": {k}, \"observation\": {}}}", obs(t)),
        _ => format!("{{\"observation\": {}}}", obs(t)),
    };
    let started = Instant::now();
    let results: Vec<Result<Vec<f64>, String>> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..clients)
            .map(|c| {
                sc.spawn(move || -> Result<Vec<f64>, String> {
                    let mut conn = Conn::new(addr).map_err(|e| e.to_string())?;
                    let mut ms = Vec::with_capacity(steps * episodes_per_client);
                    for e in 0..episodes_per_client {
                        let t0 = Instant::now();
                        let reply = conn
                            .call("POST", "/v1/episodes", &open_body(c + e))
                            .map_err(|e| e.to_string())?;
                        ms.push(t0.elapsed().as_secs_f64() * 1e3);
                        let id = reply
                            .split("\"episode\":")
                            .nth(1)
                            .and_then(|s| s.split(',').next())
                            .and_then(|s| s.trim().parse::<u64>().ok())
                            .ok_or_else(|| format!("no episode id in {reply}"))?;
                        for t in 1..steps {
                            let body = format!("{{\"reward\": -0.5, \"observation\": {}}}", obs(t));
                            let t0 = Instant::now();
                            conn.call("POST", &format!("/v1/episodes/{id}/step"), &body)
                                .map_err(|e| e.to_string())?;
                            ms.push(t0.elapsed().as_secs_f64() * 1e3);
                        }
                        conn.call("DELETE", &format!("/v1/episodes/{id}"), "")
                            .map_err(|e| e.to_string())?;
                    }
                    Ok(ms)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|_| Err("client panicked".into())))
            .collect()
    });
    let wall = started.elapsed().as_secs_f64();
    let _ = server.shutdown();
    let mut all = Vec::new();
    for r in results {
        all.extend(r.map_err(err)?);
    }
    all.sort_by(f64::total_cmp);
    Ok(ServeTiming {
        p50_ms: percentile(&all, 0.5),
        p99_ms: percentile(&all, 0.99),
        actions_per_s: all.len() as f64 / wall,
        requests: all.len(),
    })
}
