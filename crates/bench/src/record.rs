//! Benchmarks as data: one JSON record per measurement (`benchmarks/*.json`), and `BENCHMARKS.md`
//! rendered from them, so that no number in that file is typed by hand.
//!
//! A record says what was measured, the command that reproduces it, the machine, the date and the
//! commit, and holds the numbers in tables. Where a table has a reference (PyTorch, gymnasium, the
//! reference's code path), its ratio column is computed here from the two numbers, never stored.
//! `promptdt bench --json-out FILE` writes a record of its own run ([`from_report`]);
//! `promptdt bench render` regenerates `BENCHMARKS.md` ([`render_dir`]).

use crate::BenchReport;
use pdt_base::table::{Rule, Table as MdTable};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One measurement: one file under `benchmarks/`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Record {
    /// The section heading.
    pub title: String,
    /// What was measured, in a sentence or two.
    pub what: String,
    /// The commands that reproduce it, run from the repository root.
    pub commands: Vec<String>,
    pub machine: Machine,
    /// `YYYY-MM-DD`, UTC.
    pub date: String,
    /// The commit measured, where it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub commit: Option<String>,
    /// What else ran on the machine, and anything that qualifies the numbers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub conditions: Option<String>,
    /// Where the numbers come from when the command's own output is not this file (a raw archive,
    /// or the earlier hand-kept BENCHMARKS.md they were carried over from).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    pub tables: Vec<Table>,
}

/// The machine a record was measured on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Machine {
    /// CPU model and the cores used.
    pub cpu: String,
    /// GPU model, where one was used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu: Option<String>,
}

/// Rows of numbers under named columns; the first column (the case) is implicit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Table {
    /// The first column's heading (default `case`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub case: Option<String>,
    pub columns: Vec<String>,
    /// Computed columns, each `scale * columns[num] / columns[den]` (above 1: promptdt is better,
    /// when `num` is the reference's time or promptdt's rate).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ratios: Vec<Ratio>,
    pub rows: Vec<Row>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ratio {
    pub label: String,
    pub num: usize,
    pub den: usize,
    /// A factor, e.g. the runs in a pack when `den` is the pack's time per step of all its runs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Row {
    pub case: String,
    /// One per column; `null` where that column was not measured for this case.
    pub values: Vec<Option<Value>>,
}

/// A number, a median with its 10th and 90th percentiles, or the readings of repeated runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Value {
    Spread { median: f64, p10: f64, p90: f64 },
    Num(f64),
    Readings(Vec<f64>),
}

impl Value {
    /// The number a ratio uses: the median of repeated readings.
    pub fn central(&self) -> f64 {
        match self {
            Value::Num(x) | Value::Spread { median: x, .. } => *x,
            Value::Readings(v) => {
                let mut v = v.clone();
                v.sort_by(f64::total_cmp);
                match v.len() {
                    0 => f64::NAN,
                    n if n % 2 == 1 => v[n / 2],
                    n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
                }
            }
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a benchmark record: {source}")]
    Json { path: PathBuf, source: serde_json::Error },
    #[error("{path}: {field}: {why}")]
    Invalid { path: PathBuf, field: String, why: String },
}

impl Record {
    /// Checks what serde cannot: the date's form, and that every row and ratio fits its table.
    pub fn validate(&self, path: &Path) -> Result<(), RecordError> {
        let bad = |field: String, why: String| RecordError::Invalid {
            path: path.to_path_buf(),
            field,
            why,
        };
        let d = self.date.as_bytes();
        let date_ok = d.len() == 10
            && d.iter().enumerate().all(|(i, c)| {
                if i == 4 || i == 7 {
                    *c == b'-'
                } else {
                    c.is_ascii_digit()
                }
            });
        if !date_ok {
            return Err(bad("date".into(), format!("`{}` is not YYYY-MM-DD", self.date)));
        }
        if self.commands.is_empty() {
            return Err(bad("commands".into(), "no command reproduces it".into()));
        }
        if self.tables.is_empty() {
            return Err(bad("tables".into(), "no numbers".into()));
        }
        for (t, table) in self.tables.iter().enumerate() {
            let n = table.columns.len();
            for (k, r) in table.ratios.iter().enumerate() {
                if r.num >= n || r.den >= n || r.num == r.den {
                    return Err(bad(
                        format!("tables[{t}].ratios[{k}]"),
                        format!("num {} / den {} must be two of the {n} columns", r.num, r.den),
                    ));
                }
            }
            for (i, row) in table.rows.iter().enumerate() {
                let empty = |v: &Value| matches!(v, Value::Readings(r) if r.is_empty());
                if row.values.iter().flatten().any(empty) {
                    let why = "an empty list of readings".to_string();
                    return Err(bad(format!("tables[{t}].rows[{i}] ({})", row.case), why));
                }
                if row.values.len() != n {
                    return Err(bad(
                        format!("tables[{t}].rows[{i}] ({})", row.case),
                        format!("{} values for {n} columns", row.values.len()),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Reads and checks one record.
    pub fn read(path: &Path) -> Result<Self, RecordError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| RecordError::Io { path: path.to_path_buf(), source })?;
        let r: Record = serde_json::from_str(&text)
            .map_err(|source| RecordError::Json { path: path.to_path_buf(), source })?;
        r.validate(path)?;
        Ok(r)
    }

    /// Writes the record atomically (a crash leaves the old file or the new one).
    pub fn write(&self, path: &Path) -> Result<(), RecordError> {
        let mut text = serde_json::to_string_pretty(self)
            .map_err(|source| RecordError::Json { path: path.to_path_buf(), source })?;
        text.push('\n');
        pdt_base::fs::write_atomic(path, text.as_bytes())
            .map_err(|source| RecordError::Io { path: path.to_path_buf(), source })
    }

    /// The record as a Markdown section.
    pub fn markdown(&self) -> String {
        // The heading, then one paragraph: what, and how to reproduce it (a short file to scan).
        let mut s = format!("## {}\n{} ", self.title, self.what);
        let cmds: Vec<String> = self.commands.iter().map(|c| format!("`{c}`")).collect();
        let mut prov = vec![cmds.join("; ")];
        prov.push(match &self.machine.gpu {
            Some(g) => format!("{}, {}", g, self.machine.cpu),
            None => self.machine.cpu.clone(),
        });
        prov.push(match &self.commit {
            Some(c) => format!("{} at {c}", self.date),
            None => self.date.clone(),
        });
        prov.extend(self.conditions.clone());
        prov.extend(self.source.as_ref().map(|x| format!("numbers from {x}")));
        s += &format!("{}.\n", prov.join(" · "));
        for t in &self.tables {
            s.push('\n');
            s += &t.markdown();
        }
        s
    }
}

impl Table {
    fn markdown(&self) -> String {
        let mut header = vec![self.case.clone().unwrap_or_else(|| "case".into())];
        header.extend(self.columns.iter().cloned());
        header.extend(self.ratios.iter().map(|r| r.label.clone()));
        let mut t = MdTable::new(header);
        for row in &self.rows {
            let mut cells = vec![row.case.clone()];
            cells.extend(row.values.iter().map(|v| v.as_ref().map_or("-".into(), format_value)));
            for r in &self.ratios {
                let x = match (&row.values[r.num], &row.values[r.den]) {
                    (Some(a), Some(b)) if b.central() != 0.0 => {
                        format!("{:.2}x", r.scale.unwrap_or(1.0) * a.central() / b.central())
                    }
                    _ => "-".into(),
                };
                cells.push(x);
            }
            t.push(cells);
        }
        t.markdown(Rule::Tight)
    }
}

/// A number as it was recorded (Rust's shortest round-trip form), a spread as `median (p10-p90)`.
fn format_value(v: &Value) -> String {
    match v {
        Value::Num(x) => format!("{x}"),
        Value::Spread { median, p10, p90 } => format!("{median} ({p10}-{p90})"),
        Value::Readings(v) => v.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join("; "),
    }
}

/// The records of a directory: its `*.json` files in name order (not its subdirectories, which
/// hold dated history).
pub fn read_dir(dir: &Path) -> Result<Vec<(PathBuf, Record)>, RecordError> {
    let io = |source| RecordError::Io { path: dir.to_path_buf(), source };
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()
        .map_err(io)?;
    paths.retain(|p| p.is_file() && p.extension().is_some_and(|e| e == "json"));
    paths.sort();
    paths.into_iter().map(|p| Record::read(&p).map(|r| (p, r))).collect()
}

const PREAMBLE: &str = "# Benchmarks

Generated by `promptdt bench render` from the records in [`benchmarks/`](benchmarks/): do not edit
by hand. Each section is one record: what was measured, the command that reproduces it, the machine,
the date and commit. Ratios are computed from the two numbers beside them; above 1 means promptdt
is faster (a reference's time over promptdt's, or promptdt's rate over the reference's). Times are
medians, with the 10th-90th percentiles in brackets where the command reports them. The project's
CPU machine shares its 2 cores, so expect about ±20 % between runs. `promptdt bench --json-out FILE`
writes a new record; older measurements and their drivers are kept under `benchmarks/<date>/`.
";

/// `BENCHMARKS.md` from the records in `dir`.
pub fn render_dir(dir: &Path) -> Result<String, RecordError> {
    let records = read_dir(dir)?;
    let mut s = PREAMBLE.to_string();
    for (_, r) in &records {
        s.push('\n');
        s += &r.markdown();
    }
    Ok(s)
}

/// What `promptdt bench` ran, as a record. `command` is the invocation that reproduces it.
pub fn from_report(r: &BenchReport, command: String, title: Option<String>) -> Record {
    let names: Vec<&str> = r.promptdt.results.iter().map(|c| c.name.as_str()).collect();
    let threads = r.promptdt.threads;
    let mut columns =
        vec![format!("promptdt ms, {threads} thread{}", if threads == 1 { "" } else { "s" })];
    let mut ratios = Vec::new();
    if let Some(p) = &r.pytorch {
        let version = p.torch_version.as_deref().unwrap_or("?");
        columns.push(format!("PyTorch {version} ms"));
        ratios.push(Ratio { label: "PyTorch / promptdt".into(), num: 1, den: 0, scale: None });
    }
    let spread = |t: &crate::CaseTiming| {
        let [median, p10, p90] = [t.median_ms, t.p10_ms, t.p90_ms].map(significant);
        Some(Value::Spread { median, p10, p90 })
    };
    let rows = r
        .promptdt
        .results
        .iter()
        .map(|c| {
            let mut values = vec![spread(c)];
            if let Some(p) = &r.pytorch {
                values.push(p.results.iter().find(|q| q.name == c.name).and_then(spread));
            }
            Row { case: c.name.clone(), values }
        })
        .collect();
    let mut tables = vec![Table { case: None, columns, ratios, rows }];
    if !r.serve.is_empty() {
        let cols = ["p50 ms per step", "p99 ms per step", "actions/s", "requests"];
        tables.push(Table {
            case: Some("serve case".into()),
            columns: cols.map(String::from).to_vec(),
            ratios: Vec::new(),
            rows: r
                .serve
                .iter()
                .map(|c| Row {
                    case: c.name.clone(),
                    values: [c.p50_ms, c.p99_ms, c.actions_per_s, c.requests as f64]
                        .map(|x| Some(Value::Num(significant(x))))
                        .to_vec(),
                })
                .collect(),
        });
    }
    Record {
        title: title.unwrap_or_else(|| format!("promptdt bench: {}", names.join(", "))),
        what: "Milliseconds per iteration of each case (`crates/bench`), promptdt and, where a \
               Python is given, PyTorch running the same model in the same invocation."
            .into(),
        commands: vec![command],
        machine: this_machine(&r.device),
        date: today_utc(),
        commit: head_commit(),
        conditions: None,
        source: None,
        tables,
    }
}

/// `x` to 4 significant digits: what a timing's noise leaves meaningful, and a record a reader can
/// scan (a median of 19.906958999999997 ms is kept as 19.91).
fn significant(x: f64) -> f64 {
    if x == 0.0 || !x.is_finite() {
        return x;
    }
    // Dividing or multiplying by an exact power of ten, never by its inverse (0.1 is inexact).
    let e = x.abs().log10().floor() as i32 - 3;
    if e >= 0 {
        (x / 10f64.powi(e)).round() * 10f64.powi(e)
    } else {
        (x * 10f64.powi(-e)).round() / 10f64.powi(-e)
    }
}

/// The CPU model from `/proc/cpuinfo` and the cores available; the GPU's name from `nvidia-smi`
/// when the bench ran on CUDA.
fn this_machine(device: &str) -> Machine {
    let model = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|t| {
        t.lines()
            .find(|l| l.starts_with("model name"))
            .and_then(|l| l.split_once(':'))
            .map(|(_, m)| m.trim().to_string())
    });
    let cores = pdt_base::threads::available_cores();
    let cpu = format!("{}, {cores} cores", model.unwrap_or_else(|| std::env::consts::ARCH.into()));
    let gpu = device.starts_with("cuda").then(|| {
        std::process::Command::new("nvidia-smi")
            .args(["--query-gpu=name", "--format=csv,noheader"])
            .output()
            .ok()
            .and_then(|o| String::from_utf8(o.stdout).ok())
            .and_then(|s| s.lines().next().map(|l| l.trim().to_string()))
            .filter(|s| !s.is_empty())
            .unwrap_or_else(|| device.to_string())
    });
    Machine { cpu, gpu }
}

/// The checked-out commit, when run inside a git work tree with `git` on PATH.
fn head_commit() -> Option<String> {
    let o = std::process::Command::new("git")
        .args(["rev-parse", "--short=7", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())?;
    let c = String::from_utf8(o.stdout).ok()?.trim().to_string();
    (!c.is_empty()).then_some(c)
}

/// Today's date in UTC, `YYYY-MM-DD`.
fn today_utc() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    civil_date((secs / 86_400) as i64)
}

/// The proleptic Gregorian date of a day count from 1970-01-01 (H. Hinnant's `civil_from_days`).
fn civil_date(days: i64) -> String {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02}")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record() -> Record {
        Record {
            title: "T".into(),
            what: "W.".into(),
            commands: vec!["promptdt bench".into()],
            machine: Machine { cpu: "C".into(), gpu: None },
            date: "2026-11-28".into(),
            commit: Some("abc1234".into()),
            conditions: None,
            source: None,
            tables: vec![Table {
                case: None,
                columns: vec!["promptdt ms".into(), "PyTorch ms".into()],
                ratios: vec![Ratio {
                    label: "PyTorch / promptdt".into(),
                    num: 1,
                    den: 0,
                    scale: None,
                }],
                rows: vec![
                    Row {
                        case: "a".into(),
                        values: vec![
                            Some(Value::Spread { median: 2.0, p10: 1.5, p90: 2.25 }),
                            Some(Value::Num(3.0)),
                        ],
                    },
                    Row { case: "b".into(), values: vec![Some(Value::Num(1.0)), None] },
                    Row {
                        case: "c".into(),
                        values: vec![
                            Some(Value::Readings(vec![1.0, 4.0, 2.0])),
                            Some(Value::Readings(vec![5.0, 3.0])),
                        ],
                    },
                ],
            }],
        }
    }

    #[test]
    fn a_record_renders_its_numbers_and_the_computed_ratio() {
        let md = record().markdown();
        assert!(md.contains("| a | 2 (1.5-2.25) | 3 | 1.50x |"), "{md}");
        assert!(md.contains("| b | 1 | - | - |"), "{md}");
        // Repeated readings: the ratio of their medians.
        assert!(md.contains("| c | 1; 4; 2 | 5; 3 | 2.00x |"), "{md}");
        assert!(
            md.starts_with("## T\nW. `promptdt bench` · C · 2026-11-28 at abc1234.\n\n| case |"),
            "{md}"
        );
    }

    #[test]
    fn a_record_survives_json_and_bad_ones_are_named() {
        let r = record();
        let back: Record = serde_json::from_str(&serde_json::to_string(&r).unwrap()).unwrap();
        assert_eq!(back, r);
        let p = Path::new("x.json");
        let mut bad = r.clone();
        bad.tables[0].rows[1].values.pop();
        let e = bad.validate(p).unwrap_err().to_string();
        assert!(e.contains("x.json: tables[0].rows[1] (b): 1 values for 2 columns"), "{e}");
        let mut bad = r.clone();
        bad.tables[0].ratios[0].num = 2;
        assert!(bad.validate(p).unwrap_err().to_string().contains("tables[0].ratios[0]"));
        let mut bad = r;
        bad.date = "28.11.2026".into();
        assert!(bad.validate(p).unwrap_err().to_string().contains("date"));
    }

    #[test]
    fn bench_numbers_keep_four_significant_digits() {
        assert_eq!(significant(19.906958999999997), 19.91);
        assert_eq!(significant(2542.7449), 2543.0);
        assert_eq!(significant(0.09381234), 0.09381);
        assert_eq!(significant(12800.0), 12800.0);
        assert_eq!(significant(123456.0), 123500.0);
        assert_eq!(significant(0.0), 0.0);
    }

    #[test]
    fn dates_are_civil() {
        assert_eq!(civil_date(0), "1970-01-01");
        assert_eq!(civil_date(11_016), "2000-02-29");
        assert_eq!(civil_date(20_785), "2026-11-28");
    }
}
