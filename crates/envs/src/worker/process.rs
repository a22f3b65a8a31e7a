//! The worker process: started, spoken to in frames ([`super::protocol`]), watched for death and
//! hangs, and killed when dropped.
//!
//! Its stdout is read on a thread of its own, which passes each reply over a channel, so that the
//! caller can wait for a reply with a deadline (`step_timeout_s`) and kill a worker that hangs;
//! its stderr is read on another, which keeps the last lines for the error that reports its death
//! (and forwards every line to the log at debug level).

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::protocol::{read_frame, write_frame};
use super::Transport;

/// How many of the worker's last stderr lines an error quotes.
const TAIL_LINES: usize = 12;

/// A running worker process.
pub(super) struct Process {
    child: Child,
    stdin: BufWriter<ChildStdin>,
    replies: Receiver<Result<(String, Vec<f32>), String>>,
    tail: Arc<Mutex<VecDeque<String>>>,
    /// The interpreter, for messages.
    python: String,
}

impl Process {
    /// Starts `python -m promptdt.worker` with `dir` first on its `PYTHONPATH` (a suite's own
    /// `module:callable` beside the suite file imports without installing it).
    pub(super) fn spawn(python: &Path, dir: &Path) -> Result<Self, String> {
        let mut path = std::ffi::OsString::from(dir.as_os_str());
        if let Some(old) = std::env::var_os("PYTHONPATH").filter(|p| !p.is_empty()) {
            path.push(":");
            path.push(old);
        }
        let mut child = Command::new(python)
            .args(["-m", "promptdt.worker"])
            .env("PYTHONPATH", path)
            .env("PYTHONUNBUFFERED", "1")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| {
                format!(
                    "cannot start the worker's Python `{}`: {e} (set [environment] python in the \
                     suite file, or PROMPTDT_PYTHON, to an interpreter that imports promptdt)",
                    python.display()
                )
            })?;
        let (Some(stdin), Some(stdout), Some(stderr)) =
            (child.stdin.take(), child.stdout.take(), child.stderr.take())
        else {
            let _ = child.kill();
            let _ = child.wait();
            return Err("the worker's pipes were not opened (internal error)".into());
        };
        let tail = Arc::new(Mutex::new(VecDeque::with_capacity(TAIL_LINES)));
        let keep = Arc::clone(&tail);
        // Both readers end when the process's pipes close (it exited or was killed); they own
        // nothing else, so they are not joined.
        let spawned =
            std::thread::Builder::new().name("promptdt-worker-err".into()).spawn(move || {
                // Read to the end whatever it holds (bytes that are not UTF-8 included): a worker
                // whose stderr pipe were left full would block, and look hung.
                let mut err = BufReader::new(stderr);
                let mut raw = Vec::new();
                while err.read_until(b'\n', &mut raw).is_ok_and(|n| n > 0) {
                    let line = String::from_utf8_lossy(&raw).trim_end().to_owned();
                    raw.clear();
                    log::debug!("worker: {line}");
                    if let Ok(mut t) = keep.lock() {
                        if t.len() == TAIL_LINES {
                            t.pop_front();
                        }
                        t.push_back(line);
                    }
                }
            });
        let (tx, replies) = mpsc::channel();
        let reader = spawned.and_then(|_| {
            std::thread::Builder::new().name("promptdt-worker-out".into()).spawn(move || {
                let mut out = BufReader::new(stdout);
                loop {
                    let frame = read_frame(&mut out);
                    let end = frame.is_err();
                    if tx.send(frame).is_err() || end {
                        return;
                    }
                }
            })
        });
        let python = python.display().to_string();
        let mut me = Self { child, stdin: BufWriter::new(stdin), replies, tail, python };
        if let Err(e) = reader {
            me.kill();
            return Err(format!("cannot start a thread to read the worker: {e}"));
        }
        Ok(me)
    }

    /// Kills the process: what [`Transport::abandon`] asks after a reply it cannot use.
    fn stop(&mut self) {
        self.kill();
    }
}

impl Transport for Process {
    /// Sends one request and waits up to `timeout` for its reply. On any failure the process is
    /// killed and the error says what happened: it died (its exit status and last stderr lines),
    /// hung, or answered something that is not a frame.
    fn call(
        &mut self,
        header: &str,
        payload: &[f32],
        timeout: Duration,
    ) -> Result<(String, Vec<f32>), String> {
        if let Err(e) =
            write_frame(&mut self.stdin, header, payload).and_then(|()| self.stdin.flush())
        {
            return Err(self.died(&format!("could not be sent a request ({e})")));
        }
        match self.replies.recv_timeout(timeout) {
            Ok(Ok(reply)) => Ok(reply),
            Ok(Err(why)) if why.is_empty() => Err(self.died("closed its output")),
            Ok(Err(why)) => {
                self.kill();
                Err(format!("the worker sent a malformed reply: {why}"))
            }
            Err(RecvTimeoutError::Timeout) => {
                self.kill();
                Err(format!(
                    "the worker did not answer within {} s (step_timeout_s); it was killed{}",
                    timeout.as_secs_f64(),
                    self.stderr_tail()
                ))
            }
            Err(RecvTimeoutError::Disconnected) => Err(self.died("stopped answering")),
        }
    }

    fn abandon(&mut self) {
        self.stop();
    }
}

impl Process {
    /// The message for a worker that went away, with its exit status once it has one.
    fn died(&mut self, what: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(2);
        let status = loop {
            match self.child.try_wait() {
                Ok(Some(status)) => break Some(status),
                Ok(None) if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(10))
                }
                _ => break None,
            }
        };
        self.kill();
        // The stderr reader may still be draining the last lines.
        std::thread::sleep(Duration::from_millis(50));
        let status = status.map_or_else(|| "still running, killed".to_owned(), |s| s.to_string());
        format!("the worker ({}) {what}: {status}{}", self.python, self.stderr_tail())
    }

    /// `; its last stderr lines: ...`, or nothing when it wrote none.
    fn stderr_tail(&self) -> String {
        let lines: Vec<String> =
            self.tail.lock().map(|t| t.iter().cloned().collect()).unwrap_or_default();
        if lines.is_empty() {
            String::new()
        } else {
            format!("; its last stderr lines:\n  {}", lines.join("\n  "))
        }
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Process {
    /// No orphan: the worker goes with its `VecEnv`. (Were this process killed outright, the
    /// worker would see its stdin close and exit by itself.)
    fn drop(&mut self) {
        self.kill();
    }
}
