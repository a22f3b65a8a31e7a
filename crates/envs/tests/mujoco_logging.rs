//! MuJoCo's warnings go to the `log` crate, never to `MUJOCO_LOG.TXT` in the working directory.
//! (A test binary of its own, not a module of `tests/it`: the logger must be installed before the
//! first model is loaded, and the other tests load models.)

use std::sync::Mutex;

use log::{Level, LevelFilter, Log, Metadata, Record};

static RECORDS: Mutex<Vec<(Level, String, String)>> = Mutex::new(Vec::new());

struct Capture;

impl Log for Capture {
    fn enabled(&self, _: &Metadata) -> bool {
        true
    }
    fn log(&self, record: &Record) {
        if let Ok(mut r) = RECORDS.lock() {
            r.push((record.level(), record.target().to_string(), record.args().to_string()));
        }
    }
    fn flush(&self) {}
}

static LOGGER: Capture = Capture;

#[test]
fn mujoco_warnings_reach_the_log_crate_not_a_file() {
    log::set_logger(&LOGGER).unwrap_or_else(|e| panic!("{e}"));
    log::set_max_level(LevelFilter::Trace);
    let cwd = std::env::current_dir().unwrap_or_else(|e| panic!("{e}"));
    let log_file = cwd.join("MUJOCO_LOG.TXT");
    let existed = log_file.exists();
    // gym's half_cheetah.xml uses the deprecated `settotalmass`: MuJoCo warns when loading it.
    let fam = pdt_envs::family("cheetah_dir").unwrap_or_else(|e| panic!("{e}"));
    let _env = fam.make(0).unwrap_or_else(|e| panic!("{e}"));
    let records = RECORDS.lock().map(|r| r.clone()).unwrap_or_default();
    assert!(
        records.iter().any(|(lvl, target, msg)| *lvl == Level::Warn
            && target.starts_with("mujoco")
            && msg.contains("settotalmass")),
        "no settotalmass warning in {records:?}"
    );
    assert!(existed || !log_file.exists(), "MuJoCo wrote {}", log_file.display());
}
