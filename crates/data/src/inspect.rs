//! Summaries of data files for people: what is in a reference pickle or a native file, and a
//! plain-text table of them.

use std::cmp::Ordering;
use std::fs;
use std::path::{Path, PathBuf};

use pdt_base::table::{Align, Table};
use serde::Serialize;

use crate::reference::{load_pickle, ArrayInfo, ReferenceOptions};
use crate::{native, DataError, TaskDataset};

/// `FileReport::format` of a reference-release pickle.
pub const FORMAT_REFERENCE_PICKLE: &str = "reference-pickle";
/// `FileReport::format` of a native safetensors file.
pub const FORMAT_NATIVE: &str = "native";

/// What one data file holds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FileReport {
    pub path: PathBuf,
    /// [`FORMAT_REFERENCE_PICKLE`] or [`FORMAT_NATIVE`].
    pub format: &'static str,
    pub trajectories: usize,
    pub steps: usize,
    pub obs_dim: usize,
    pub act_dim: usize,
    /// The arrays as stored, with their shapes in the first trajectory.
    pub dtypes: Vec<ArrayInfo>,
    pub return_min: f64,
    pub return_mean: f64,
    pub return_max: f64,
    pub length_min: usize,
    pub length_max: usize,
}

/// Reports on a file, or on every `*.pkl` and `*.safetensors` file directly in a directory, in
/// natural order of their names (`cheetah_vel-2` before `cheetah_vel-10`). Fails on the first file
/// that cannot be read. In a directory, every entry with a data file's name that is not a readable
/// regular file (a symbolic link loop, a dangling link, a directory, a FIFO) is named in the error
/// with what it is; a directory with no data files names the entries it could not follow, whatever
/// their names, since they may be the data files.
pub fn inspect_path(path: &Path) -> Result<Vec<FileReport>, DataError> {
    let io = |source| DataError::Io { path: path.into(), source };
    if !fs::metadata(path).map_err(io)?.is_dir() {
        return Ok(vec![inspect_file(path)?]);
    }
    let mut files = Vec::new();
    // Data names that are not regular files, and other entries that cannot be followed.
    let (mut bad_data, mut bad_other) = (Vec::new(), Vec::new());
    for entry in fs::read_dir(path).map_err(io)? {
        let file = entry.map_err(io)?.path();
        let ext = file.extension().and_then(|e| e.to_str());
        let data_name = matches!(ext, Some("pkl" | "safetensors"));
        match fs::metadata(&file) {
            Ok(m) if m.is_file() => {
                if data_name {
                    files.push(file);
                }
            }
            Ok(m) => {
                if data_name {
                    bad_data.push((file, crate::multitask::file_kind(&m.file_type()).to_string()));
                }
            }
            Err(e) => {
                let why = unfollowable(&file, &e);
                if data_name { &mut bad_data } else { &mut bad_other }.push((file, why));
            }
        }
    }
    let list = |mut bad: Vec<(PathBuf, String)>| {
        bad.sort_by(|a, b| natural_cmp(&file_label(&a.0), &file_label(&b.0)));
        let items: Vec<String> =
            bad.iter().map(|(f, why)| format!("{}: {why}", file_label(f))).collect();
        items.join("; ")
    };
    if !bad_data.is_empty() {
        let n = bad_data.len();
        return Err(DataError::Format {
            path: path.into(),
            message: format!(
                "{n} entr{} named as data file{} cannot be read as one: {}",
                if n == 1 { "y" } else { "ies" },
                if n == 1 { "" } else { "s" },
                list(bad_data)
            ),
        });
    }
    if files.is_empty() {
        let mut message = "no .pkl or .safetensors files in this directory".to_string();
        if !bad_other.is_empty() {
            message.push_str(&format!(" (entries that cannot be followed: {})", list(bad_other)));
        }
        return Err(DataError::Format { path: path.into(), message });
    }
    files.sort_by(|a, b| natural_cmp(&file_label(a), &file_label(b)));
    files.iter().map(|f| inspect_file(f)).collect()
}

/// Why `fs::metadata` of a directory entry failed, in words: a dangling link names its target, a
/// link loop is called one.
fn unfollowable(file: &Path, e: &std::io::Error) -> String {
    let is_link = fs::symlink_metadata(file).is_ok_and(|m| m.file_type().is_symlink());
    if !is_link {
        return e.to_string();
    }
    let target = fs::read_link(file).map(|t| t.display().to_string()).unwrap_or_default();
    if e.kind() == std::io::ErrorKind::NotFound {
        format!("a symbolic link to {target}, which does not exist")
    } else {
        // ELOOP ("too many levels of symbolic links") for a loop; its number differs by OS.
        format!("a symbolic link to {target} that cannot be followed ({e})")
    }
}

/// Reports on one file: `.safetensors` is read as the native format, anything else as a
/// reference pickle.
pub fn inspect_file(path: &Path) -> Result<FileReport, DataError> {
    if path.extension().and_then(|e| e.to_str()) == Some(native::FILE_EXTENSION) {
        let dataset = native::read_task_dataset(path)?;
        let dtypes = native_arrays(&dataset);
        Ok(report(path, FORMAT_NATIVE, &dataset, dtypes))
    } else {
        let loaded = load_pickle(path, &ReferenceOptions::default())?;
        Ok(report(path, FORMAT_REFERENCE_PICKLE, &loaded.dataset, loaded.arrays))
    }
}

/// The native format's arrays, shaped as in the first trajectory (like [`ArrayInfo`] for
/// pickles): floats are float32, flags uint8.
fn native_arrays(ds: &TaskDataset) -> Vec<ArrayInfo> {
    let t = ds.trajectories.first().map_or(0, |t| t.len());
    let info = |key: &str, dtype: &str, shape: Vec<usize>| ArrayInfo {
        key: key.into(),
        dtype: dtype.into(),
        shape,
    };
    vec![
        info("observations", "float32", vec![t, ds.obs_dim]),
        info("actions", "float32", vec![t, ds.act_dim]),
        info("rewards", "float32", vec![t]),
        info("terminated", "uint8", vec![t]),
        info("truncated", "uint8", vec![t]),
    ]
}

fn report(
    path: &Path,
    format: &'static str,
    ds: &TaskDataset,
    dtypes: Vec<ArrayInfo>,
) -> FileReport {
    let returns = ds.returns();
    let lengths: Vec<usize> = ds.trajectories.iter().map(|t| t.len()).collect();
    let n = returns.len();
    let (return_min, return_mean, return_max) = if n == 0 {
        (0.0, 0.0, 0.0)
    } else {
        (
            returns.iter().copied().fold(f64::INFINITY, f64::min),
            returns.iter().sum::<f64>() / n as f64,
            returns.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        )
    };
    FileReport {
        path: path.to_path_buf(),
        format,
        trajectories: n,
        steps: ds.num_steps(),
        obs_dim: ds.obs_dim,
        act_dim: ds.act_dim,
        dtypes,
        return_min,
        return_mean,
        return_max,
        length_min: lengths.iter().copied().min().unwrap_or(0),
        length_max: lengths.iter().copied().max().unwrap_or(0),
    }
}

fn file_label(path: &Path) -> String {
    match path.file_name() {
        Some(name) => name.to_string_lossy().into_owned(),
        None => path.display().to_string(),
    }
}

/// Orders names as a person would: runs of digits compare as numbers, so `task-2` < `task-10`.
/// Names equal under that rule (`a01`, `a1`) fall back to plain string order.
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (mut x, mut y) = (a, b);
    loop {
        let (cx, rx) = split_run(x);
        let (cy, ry) = split_run(y);
        if cx.is_empty() || cy.is_empty() {
            return cx.len().cmp(&cy.len()).then_with(|| a.cmp(b));
        }
        let both_digits = cx.starts_with(|c: char| c.is_ascii_digit())
            && cy.starts_with(|c: char| c.is_ascii_digit());
        let ord = if both_digits {
            let (nx, ny) = (cx.trim_start_matches('0'), cy.trim_start_matches('0'));
            nx.len().cmp(&ny.len()).then_with(|| nx.cmp(ny))
        } else {
            cx.cmp(cy)
        };
        if ord != Ordering::Equal {
            return ord;
        }
        (x, y) = (rx, ry);
    }
}

/// Splits off the leading run of ASCII digits, or of non-digits.
fn split_run(s: &str) -> (&str, &str) {
    let digits = s.starts_with(|c: char| c.is_ascii_digit());
    let end = s.find(|c: char| c.is_ascii_digit() != digits).unwrap_or(s.len());
    s.split_at(end)
}

/// An aligned plain-text table, one row per file, and a summary line.
pub fn render_table(reports: &[FileReport]) -> String {
    let headers =
        ["file", "format", "trajs", "steps", "obs", "act", "length", "return min", "mean", "max"];
    // Text columns are left-aligned, numbers right-aligned.
    let (text, num) = (Align::Left, Align::Right);
    let align = vec![text, text, num, num, num, num, num, num, num, num];
    let mut table = Table::with_align(headers.map(String::from).to_vec(), align);
    for r in reports {
        let length = if r.length_min == r.length_max {
            r.length_min.to_string()
        } else {
            format!("{}-{}", r.length_min, r.length_max)
        };
        table.push(vec![
            file_label(&r.path),
            r.format.to_string(),
            r.trajectories.to_string(),
            r.steps.to_string(),
            r.obs_dim.to_string(),
            r.act_dim.to_string(),
            length,
            format!("{:.2}", r.return_min),
            format!("{:.2}", r.return_mean),
            format!("{:.2}", r.return_max),
        ]);
    }
    let mut out = table.aligned_text();
    let trajectories: usize = reports.iter().map(|r| r.trajectories).sum();
    let steps: usize = reports.iter().map(|r| r.steps).sum();
    let files = reports.len();
    out.push_str(&format!(
        "{files} file{}, {trajectories} trajectories, {steps} steps\n",
        if files == 1 { "" } else { "s" }
    ));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order() {
        let mut names = vec![
            "cheetah_vel-10-prompt-expert.pkl",
            "cheetah_vel-2-prompt-expert.pkl",
            "cheetah_dir-1-prompt-expert.pkl",
            "cheetah_vel-1-prompt-expert.pkl",
            "a01",
            "a1",
            "a",
            "cheetah_vel-2-expert.pkl",
        ];
        names.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            names,
            vec![
                "a",
                "a01",
                "a1",
                "cheetah_dir-1-prompt-expert.pkl",
                "cheetah_vel-1-prompt-expert.pkl",
                "cheetah_vel-2-expert.pkl",
                "cheetah_vel-2-prompt-expert.pkl",
                "cheetah_vel-10-prompt-expert.pkl",
            ]
        );
    }

    #[test]
    fn table_is_aligned_with_summary() {
        let r = |name: &str, ret: f64| FileReport {
            path: PathBuf::from(format!("/data/{name}")),
            format: FORMAT_REFERENCE_PICKLE,
            trajectories: 5,
            steps: 1000,
            obs_dim: 20,
            act_dim: 6,
            dtypes: vec![],
            return_min: ret - 1.0,
            return_mean: ret,
            return_max: ret + 1.0,
            length_min: 200,
            length_max: 200,
        };
        let table = render_table(&[r("a-2.pkl", -16.0), r("longer-name-10.pkl", 1150.123)]);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 5, "{table}");
        assert!(lines[0].starts_with("file"));
        assert!(lines[2].contains("-16.00") && lines[3].contains("1150.12"), "{table}");
        // Right-aligned numbers: every row ends at the same column.
        assert_eq!(lines[2].len(), lines[3].len(), "{table}");
        assert_eq!(lines[4], "2 files, 10 trajectories, 2000 steps");
    }
}
