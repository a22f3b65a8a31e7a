//! Writing a task's dataset as one safetensors file, atomically.

use super::*;

/// Writes `ds` to `path` in the native format, atomically: the bytes go to a temporary file in the
/// same directory, which is fsynced and then renamed over `path`, so a reader (or a crash) sees
/// either the old file or the complete new one, never a partial file. On error the temporary file
/// is removed and an existing `path` is left untouched.
///
/// The dataset is validated first with the reader's rules (finite values, flags only at an
/// episode's last step, consistent shapes), so every file written here can be read back.
pub fn write_task_dataset(path: &Path, ds: &TaskDataset, meta: &FileMeta) -> Result<(), DataError> {
    if ds.trajectories.is_empty() {
        return Err(DataError::Empty.in_file(path));
    }
    if ds.obs_dim == 0 || ds.act_dim == 0 {
        return Err(shape_err(
            path,
            "dims",
            "obs_dim >= 1 and act_dim >= 1".into(),
            format!("obs_dim {}, act_dim {}", ds.obs_dim, ds.act_dim),
        ));
    }
    for (i, t) in ds.trajectories.iter().enumerate() {
        check_trajectory(i, t, ds.obs_dim, ds.act_dim).map_err(|m| format_err(path, m))?;
    }
    let n = ds.num_steps();
    let columns = [
        Column::new(ds, ColumnKind::Observations, vec![n, ds.obs_dim]),
        Column::new(ds, ColumnKind::Actions, vec![n, ds.act_dim]),
        Column::new(ds, ColumnKind::Rewards, vec![n]),
        Column::new(ds, ColumnKind::Terminated, vec![n]),
        Column::new(ds, ColumnKind::Truncated, vec![n]),
        Column::new(ds, ColumnKind::EpisodeStarts, vec![ds.trajectories.len() + 1]),
    ];
    let metadata = Some(meta.to_safetensors_map());
    write_atomically(path, |tmp| {
        safetensors::serialize_to_file(columns.iter().map(|c| (c.kind.name(), c)), &metadata, tmp)
            .map_err(|e| match e {
                SafeTensorError::IoError(source) => {
                    DataError::Io { path: tmp.to_path_buf(), source }
                }
                other => format_err(path, format!("safetensors serialization failed: {other}")),
            })?;
        canonicalize_header(tmp).map_err(|source| DataError::Io { path: tmp.to_path_buf(), source })
    })
}

/// Rewrites a safetensors header with its JSON keys sorted, in place. The safetensors crate writes
/// `__metadata__` from a `HashMap`, whose order changes from run to run; sorted keys make the same
/// data give the same bytes. Reordering keys keeps the JSON's length, and the header is padded with
/// spaces to its original size, so the tensor offsets are untouched.
fn canonicalize_header(path: &Path) -> std::io::Result<()> {
    use std::io::{Read, Seek, SeekFrom, Write};
    let mut f = std::fs::OpenOptions::new().read(true).write(true).open(path)?;
    let mut len = [0u8; 8];
    f.read_exact(&mut len)?;
    let n = u64::from_le_bytes(len) as usize;
    let mut header = vec![0u8; n];
    f.read_exact(&mut header)?;
    let invalid = |m: String| std::io::Error::new(std::io::ErrorKind::InvalidData, m);
    // serde_json's map is a BTreeMap: parsing and printing sorts every object's keys.
    let value: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| invalid(e.to_string()))?;
    let mut sorted = serde_json::to_vec(&value).map_err(|e| invalid(e.to_string()))?;
    if sorted.len() > n {
        return Err(invalid(format!(
            "canonical header is {} bytes, more than the {n} written",
            sorted.len()
        )));
    }
    sorted.resize(n, b' ');
    f.seek(SeekFrom::Start(8))?;
    f.write_all(&sorted)?;
    f.sync_all()
}

#[derive(Clone, Copy)]
enum ColumnKind {
    Observations,
    Actions,
    Rewards,
    Terminated,
    Truncated,
    EpisodeStarts,
}

impl ColumnKind {
    fn name(self) -> &'static str {
        match self {
            ColumnKind::Observations => OBSERVATIONS,
            ColumnKind::Actions => ACTIONS,
            ColumnKind::Rewards => REWARDS,
            ColumnKind::Terminated => TERMINATED,
            ColumnKind::Truncated => TRUNCATED,
            ColumnKind::EpisodeStarts => EPISODE_STARTS,
        }
    }

    fn dtype(self) -> Dtype {
        match self {
            ColumnKind::Observations | ColumnKind::Actions | ColumnKind::Rewards => Dtype::F32,
            ColumnKind::Terminated | ColumnKind::Truncated => Dtype::U8,
            ColumnKind::EpisodeStarts => Dtype::I64,
        }
    }
}

/// One tensor of the file, concatenated from the trajectories only when safetensors asks for its
/// bytes: `serialize_to_file` writes one tensor at a time, so the writer holds at most one
/// concatenated column in memory rather than a second copy of the whole dataset.
struct Column<'a> {
    ds: &'a TaskDataset,
    kind: ColumnKind,
    shape: Vec<usize>,
}

impl<'a> Column<'a> {
    fn new(ds: &'a TaskDataset, kind: ColumnKind, shape: Vec<usize>) -> Self {
        Self { ds, kind, shape }
    }

    fn bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.data_len());
        let f32s = |out: &mut Vec<u8>, v: &[f32]| {
            out.extend(v.iter().flat_map(|x| x.to_le_bytes()));
        };
        for t in &self.ds.trajectories {
            match self.kind {
                ColumnKind::Observations => f32s(&mut out, &t.observations),
                ColumnKind::Actions => f32s(&mut out, &t.actions),
                ColumnKind::Rewards => f32s(&mut out, &t.rewards),
                ColumnKind::Terminated => out.extend(t.terminated.iter().map(|&b| u8::from(b))),
                ColumnKind::Truncated => out.extend(t.truncated.iter().map(|&b| u8::from(b))),
                ColumnKind::EpisodeStarts => {}
            }
        }
        if let ColumnKind::EpisodeStarts = self.kind {
            let mut offset = 0i64;
            out.extend(offset.to_le_bytes());
            for t in &self.ds.trajectories {
                // A Vec cannot hold more than isize::MAX elements, so a step count fits in i64.
                offset += t.len() as i64;
                out.extend(offset.to_le_bytes());
            }
        }
        out
    }
}

impl View for &Column<'_> {
    fn dtype(&self) -> Dtype {
        self.kind.dtype()
    }

    fn shape(&self) -> &[usize] {
        &self.shape
    }

    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Owned(self.bytes())
    }

    fn data_len(&self) -> usize {
        self.shape.iter().product::<usize>() * self.kind.dtype().size()
    }
}

/// Writes `bytes` to `path` atomically: a uniquely named temporary file beside it, fsynced, then
/// renamed over `path`, so a crash leaves the old file or the new one, never a torn one.
pub fn write_bytes_atomically(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    write_atomically(path, |tmp| fs::write(tmp, bytes).map_err(io_err(tmp)))
}

/// Writes a file through `write(temp_path)`, then fsyncs and renames it to `path`
/// (`pdt_base::fs::write_atomic_with`: a uniquely named temporary beside it, removed on failure).
pub(crate) fn write_atomically(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), DataError>,
) -> Result<(), DataError> {
    if path.is_dir() {
        // rename() would also refuse, but with a less helpful message.
        return Err(format_err(path, "is a directory; cannot write a dataset file over it"));
    }
    let mut inner: Option<DataError> = None;
    pdt_base::fs::write_atomic_with(path, |tmp| {
        write(tmp).map_err(|e| {
            let message = e.to_string();
            inner = Some(e);
            std::io::Error::other(message)
        })
    })
    .map_err(|e| inner.take().unwrap_or_else(|| DataError::Io { path: path.into(), source: e }))
}
