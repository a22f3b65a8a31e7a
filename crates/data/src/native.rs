//! The native on-disk format: one plain [safetensors] file per (task, kind), plus an optional
//! `dataset.json` card per directory. The full specification is `docs/data-format.md`.
//!
//! A file `{env}-{index}-{mode}.safetensors` (named like the reference release's pickles, so the two
//! are interchangeable) holds the steps of all its episodes concatenated:
//!
//! | tensor           | dtype | shape          |
//! |------------------|-------|----------------|
//! | `observations`   | F32   | `[N, obs_dim]` |
//! | `actions`        | F32   | `[N, act_dim]` |
//! | `rewards`        | F32   | `[N]`          |
//! | `terminated`     | U8    | `[N]`          |
//! | `truncated`      | U8    | `[N]`          |
//! | `episode_starts` | I64   | `[E + 1]`      |
//!
//! `episode_starts` holds the offsets of the episodes: episode `e` is steps
//! `episode_starts[e]..episode_starts[e + 1]`; the first entry is 0 and the last is `N`. The
//! safetensors `__metadata__` map carries `format = "promptdt-trajectories"`, `format_version = "1"`
//! and, when known, `env`, `task_index` and `mode`.
//!
//! Everything a file needs is in the file: [`read_task_dataset`] never looks at the card.
//!
//! [safetensors]: https://github.com/huggingface/safetensors

use std::borrow::Cow;
use std::collections::HashMap;
use std::fs;
use std::io::Read;
use std::path::Path;

use safetensors::tensor::{Dtype, Metadata, SafeTensorError, View};
use serde::{Deserialize, Serialize};

use crate::{DataError, TaskDataset, Trajectory};

/// Value of the `format` metadata key.
pub const FORMAT_NAME: &str = "promptdt-trajectories";
/// Value of the `format_version` metadata key written by, and the only one understood by, this
/// crate.
pub const FORMAT_VERSION: &str = "1";
/// File extension of native trajectory files (without the dot).
pub const FILE_EXTENSION: &str = "safetensors";
/// Name of the optional per-directory dataset card.
pub const CARD_FILE_NAME: &str = "dataset.json";
/// Value of the card's `format` key.
pub const CARD_FORMAT_NAME: &str = "promptdt-dataset";
/// Largest safetensors JSON header this reader accepts. Headers written here are well under 1 KiB
/// (six tensors and five short strings); the bound stops a corrupt or hostile length prefix from
/// making us read or parse a huge header. The safetensors crate's own bound is 100 MB.
pub const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Tensor names, as they appear in the file.
pub mod tensor_names {
    pub const OBSERVATIONS: &str = "observations";
    pub const ACTIONS: &str = "actions";
    pub const REWARDS: &str = "rewards";
    pub const TERMINATED: &str = "terminated";
    pub const TRUNCATED: &str = "truncated";
    pub const EPISODE_STARTS: &str = "episode_starts";
}
use tensor_names::*;

/// Metadata keys, as they appear in the safetensors `__metadata__` map.
pub mod meta_keys {
    pub const FORMAT: &str = "format";
    pub const FORMAT_VERSION: &str = "format_version";
    pub const ENV: &str = "env";
    pub const TASK_INDEX: &str = "task_index";
    pub const MODE: &str = "mode";
}

/// What a file says about itself in its `__metadata__`: which task and which kind of set it holds.
/// Every field is optional: a file stays readable without them.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileMeta {
    /// Environment family, e.g. `cheetah_vel`.
    pub env: Option<String>,
    /// Task index within the family, e.g. `2`.
    pub task_index: Option<usize>,
    /// Kind of set, e.g. `expert`, `medium`, `prompt-expert`.
    pub mode: Option<String>,
}

impl FileMeta {
    /// All three fields known.
    pub fn new(env: impl Into<String>, task_index: usize, mode: impl Into<String>) -> Self {
        Self { env: Some(env.into()), task_index: Some(task_index), mode: Some(mode.into()) }
    }

    /// Parses a file name `{env}-{index}-{mode}.{ext}` (or a bare stem); `None` if it does not
    /// follow the convention. See [`parse_task_file_stem`].
    pub fn from_file_name(path: &Path) -> Option<Self> {
        let stem = path.file_stem()?.to_str()?;
        let (env, index, mode) = parse_task_file_stem(stem)?;
        Some(Self::new(env, index, mode))
    }

    /// The conventional file name `{env}-{index}-{mode}.safetensors`, when all fields are known.
    pub fn file_name(&self) -> Option<String> {
        match (&self.env, self.task_index, &self.mode) {
            (Some(env), Some(index), Some(mode)) => {
                Some(format!("{}.{FILE_EXTENSION}", task_file_stem(env, index, mode)))
            }
            _ => None,
        }
    }

    fn to_safetensors_map(&self) -> HashMap<String, String> {
        let mut map = HashMap::new();
        map.insert(meta_keys::FORMAT.to_owned(), FORMAT_NAME.to_owned());
        map.insert(meta_keys::FORMAT_VERSION.to_owned(), FORMAT_VERSION.to_owned());
        if let Some(env) = &self.env {
            map.insert(meta_keys::ENV.to_owned(), env.clone());
        }
        if let Some(index) = self.task_index {
            map.insert(meta_keys::TASK_INDEX.to_owned(), index.to_string());
        }
        if let Some(mode) = &self.mode {
            map.insert(meta_keys::MODE.to_owned(), mode.clone());
        }
        map
    }

    /// Reads the metadata map, checking `format` and `format_version` when present. Files that
    /// omit them (e.g. written by hand from Python) are taken as version 1.
    fn from_safetensors_map(
        path: &Path,
        map: Option<&HashMap<String, String>>,
    ) -> Result<Self, DataError> {
        let Some(map) = map else { return Ok(Self::default()) };
        if let Some(format) = map.get(meta_keys::FORMAT) {
            if format != FORMAT_NAME {
                return Err(format_err(
                    path,
                    format!(
                        "metadata `{}` is {format:?}, expected {FORMAT_NAME:?}: not a \
                         promptdt trajectory file",
                        meta_keys::FORMAT
                    ),
                ));
            }
        }
        if let Some(version) = map.get(meta_keys::FORMAT_VERSION) {
            if version != FORMAT_VERSION {
                return Err(format_err(
                    path,
                    format!(
                        "metadata `{}` is {version:?}; this reader understands only \
                         {FORMAT_VERSION:?}",
                        meta_keys::FORMAT_VERSION
                    ),
                ));
            }
        }
        let task_index = match map.get(meta_keys::TASK_INDEX) {
            None => None,
            Some(s) => Some(s.parse::<usize>().map_err(|_| {
                format_err(
                    path,
                    format!(
                        "metadata `{}` is {s:?}, expected a non-negative integer",
                        meta_keys::TASK_INDEX
                    ),
                )
            })?),
        };
        Ok(Self {
            env: map.get(meta_keys::ENV).cloned(),
            task_index,
            mode: map.get(meta_keys::MODE).cloned(),
        })
    }
}

/// The conventional stem `{env}-{index}-{mode}`, e.g. `cheetah_vel-2-prompt-expert`.
pub fn task_file_stem(env: &str, index: usize, mode: &str) -> String {
    format!("{env}-{index}-{mode}")
}

/// Splits a stem `{env}-{index}-{mode}` into its parts. Both `env` (`ML1-pick-place-v2`) and `mode`
/// (`prompt-expert`) may contain `-`, so the index is taken to be the *last* all-digit `-`-separated
/// piece that has a non-empty env before it and a non-empty mode after it.
pub fn parse_task_file_stem(stem: &str) -> Option<(String, usize, String)> {
    let pieces: Vec<&str> = stem.split('-').collect();
    // Last candidate position first; positions 0 and len-1 cannot work (empty env / mode).
    (1..pieces.len().saturating_sub(1)).rev().find_map(|i| {
        let piece = pieces[i];
        if piece.is_empty() || !piece.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        let index = piece.parse::<usize>().ok()?;
        let env = pieces[..i].join("-");
        let mode = pieces[i + 1..].join("-");
        (!env.is_empty() && !mode.is_empty()).then_some((env, index, mode))
    })
}

fn format_err(path: &Path, message: impl Into<String>) -> DataError {
    DataError::Format { path: path.to_path_buf(), message: message.into() }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DataError + '_ {
    move |source| DataError::Io { path: path.to_path_buf(), source }
}

fn shape_err(path: &Path, field: &'static str, expected: String, got: String) -> DataError {
    DataError::Shape { field, expected, got }.in_file(path)
}

// ---------------------------------------------------------------------------------------------
// Checks shared by the writer and the reader
// ---------------------------------------------------------------------------------------------

/// Checks one trajectory against the format's rules; the message names the array, the step and
/// (for vectors) the component at fault. The writer runs it so that it never writes a file the
/// reader would reject; the reader runs it on what it decoded.
fn check_trajectory(
    index: usize,
    t: &Trajectory,
    obs_dim: usize,
    act_dim: usize,
) -> Result<(), String> {
    let len = t.rewards.len();
    if len == 0 {
        return Err(format!("episode {index} is empty (every episode needs >= 1 step)"));
    }
    if t.obs_dim != obs_dim || t.act_dim != act_dim {
        return Err(format!(
            "episode {index} has obs_dim {}, act_dim {}; the dataset has {obs_dim}, {act_dim}",
            t.obs_dim, t.act_dim
        ));
    }
    for (name, got, want) in [
        (OBSERVATIONS, t.observations.len(), len * obs_dim),
        (ACTIONS, t.actions.len(), len * act_dim),
        (TERMINATED, t.terminated.len(), len),
        (TRUNCATED, t.truncated.len(), len),
    ] {
        if got != want {
            return Err(format!(
                "episode {index}: `{name}` has {got} elements, expected {want} ({len} steps)"
            ));
        }
    }
    check_finite(index, OBSERVATIONS, &t.observations, obs_dim)?;
    check_finite(index, ACTIONS, &t.actions, act_dim)?;
    check_finite(index, REWARDS, &t.rewards, 1)?;
    // A flag ends an episode, so it may only be set at its last step. (Both may be set there:
    // a time limit can coincide with a true termination.)
    for (name, flags) in [(TERMINATED, &t.terminated), (TRUNCATED, &t.truncated)] {
        if let Some(step) = flags[..len - 1].iter().position(|&f| f) {
            return Err(format!(
                "episode {index}: `{name}` is set at step {step} of {len}, but an episode's \
                 terminated/truncated flags are only allowed at its last step (split the episode \
                 there, or clear the flag)"
            ));
        }
    }
    Ok(())
}

fn check_finite(episode: usize, name: &str, values: &[f32], width: usize) -> Result<(), String> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => {
            let at = if width == 1 {
                format!("step {i}")
            } else {
                format!("step {}, component {}", i / width, i % width)
            };
            Err(format!(
                "episode {episode}: `{name}` is {} at {at}; the format stores finite values only",
                values[i]
            ))
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Writing
// ---------------------------------------------------------------------------------------------

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

// ---------------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------------

/// Reads only the metadata of a native file (the header; the tensor data is not read).
pub fn read_file_meta(path: &Path) -> Result<FileMeta, DataError> {
    // A FIFO or device is refused before it is opened (opening a FIFO would block).
    let (mut file, file_len) = pdt_base::fs::open_regular(path).map_err(io_err(path))?;
    let mut prefix = [0u8; 8];
    if file_len < 8 {
        return Err(too_short(path, file_len));
    }
    file.read_exact(&mut prefix).map_err(io_err(path))?;
    let header_len = check_header_len(path, u64::from_le_bytes(prefix), file_len)?;
    // Bounded by MAX_HEADER_BYTES and by the file size, so this allocation is small.
    let mut header = vec![0u8; header_len];
    file.read_exact(&mut header).map_err(io_err(path))?;
    let metadata = parse_header(path, &header)?;
    FileMeta::from_safetensors_map(path, metadata.metadata().as_ref())
}

/// Files up to this size are read into memory; larger ones are memory-mapped. Reading costs a
/// second copy of the file for the duration of the decode, which is nothing for the files of a
/// real run (the largest in the reference release is a few hundred MB, most are a few MB) but
/// makes the reader immune to the file changing under it: a mapped file that another process
/// truncates while it is decoded kills the reader with SIGBUS, with no message. Above the bound
/// the copy would cost real memory, so those files are mapped and carry that caveat
/// (`docs/data-format.md`, "Reading while another process writes").
pub const MAX_READ_INTO_MEMORY_BYTES: u64 = 256 << 20;

/// Reads and fully validates a native file: dtypes and shapes of every tensor, episode offsets
/// (start at 0, end at `N`, strictly increasing: no empty episode), `obs_dim, act_dim >= 1`, finite
/// floats, 0/1 flags set only at an episode's last step, and the metadata's `format` /
/// `format_version` when present. Tensors with other names are ignored.
pub fn read_task_dataset(path: &Path) -> Result<TaskDataset, DataError> {
    read_task_dataset_with_meta(path).map(|(ds, _)| ds)
}

/// [`read_task_dataset`], also returning what the file's metadata says about itself.
pub fn read_task_dataset_with_meta(path: &Path) -> Result<(TaskDataset, FileMeta), DataError> {
    let (file, file_len) = pdt_base::fs::open_regular(path).map_err(io_err(path))?;
    if file_len < 8 {
        // Also avoids mapping an empty file, which mmap rejects.
        return Err(too_short(path, file_len));
    }
    if file_len <= MAX_READ_INTO_MEMORY_BYTES {
        // A file truncated or rewritten while it is read gives short or mixed bytes here, which
        // `decode` refuses with a message (truncated file, bad offsets, ...), never a signal.
        let mut bytes = Vec::with_capacity(file_len as usize);
        file.take(MAX_READ_INTO_MEMORY_BYTES + 1).read_to_end(&mut bytes).map_err(io_err(path))?;
        return decode(path, &bytes);
    }
    // Memory-map rather than read: the data is decoded straight from the page cache into the
    // per-episode vectors, so a file is copied once instead of twice and peak memory is the
    // dataset rather than dataset + file.
    //
    // SAFETY: a mapping is undefined behaviour if the file changes while mapped. The file is
    // opened read-only, every byte is copied out (decoded) before this function returns, and the
    // map is dropped then. This crate never modifies a dataset file in place: writers replace
    // files by renaming a new file over the name (`write_atomically`), which leaves the inode we
    // mapped unchanged. Only a foreign process truncating or rewriting the file in place during
    // the read could break this (the process then dies with SIGBUS), the same caveat every
    // mmap-based safetensors loader carries; `docs/data-format.md` says so.
    #[allow(unsafe_code)]
    let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io_err(path))?;
    decode(path, &map)
}

fn too_short(path: &Path, len: u64) -> DataError {
    format_err(
        path,
        format!(
            "file is {len} bytes, too short for a safetensors file (8-byte header length + \
             header): truncated or not a safetensors file"
        ),
    )
}

/// Checks the 8-byte little-endian header length against our bound and the file size, before
/// anything is allocated or parsed from it.
fn check_header_len(path: &Path, header_len: u64, file_len: u64) -> Result<usize, DataError> {
    if header_len > MAX_HEADER_BYTES {
        return Err(format_err(
            path,
            format!(
                "header length prefix says {header_len} bytes, over the {MAX_HEADER_BYTES}-byte \
                 limit: corrupt or not a safetensors file"
            ),
        ));
    }
    if header_len > file_len - 8 {
        return Err(format_err(
            path,
            format!(
                "header length prefix says {header_len} bytes but only {} bytes follow it: \
                 truncated file",
                file_len - 8
            ),
        ));
    }
    // <= MAX_HEADER_BYTES, so it fits in usize on every supported platform.
    usize::try_from(header_len)
        .map_err(|_| format_err(path, format!("header length {header_len} does not fit in memory")))
}

/// Parses the JSON header with serde directly (rather than through `SafeTensors::read_metadata`)
/// to keep serde's message, which says what is wrong (bad dtype name, bad JSON, ...).
fn parse_header(path: &Path, header: &[u8]) -> Result<Metadata, DataError> {
    let text = std::str::from_utf8(header)
        .map_err(|e| format_err(path, format!("safetensors header is not UTF-8: {e}")))?;
    serde_json::from_str::<Metadata>(text)
        .map_err(|e| format_err(path, format!("safetensors header is invalid: {e}")))
}

/// A tensor located in the file, not yet decoded.
struct Raw<'a> {
    name: &'static str,
    dtype: Dtype,
    shape: Vec<usize>,
    bytes: &'a [u8],
}

fn decode(path: &Path, buf: &[u8]) -> Result<(TaskDataset, FileMeta), DataError> {
    let file_len = buf.len() as u64;
    let mut prefix = [0u8; 8];
    prefix.copy_from_slice(buf.get(..8).ok_or_else(|| too_short(path, file_len))?);
    let header_len = check_header_len(path, u64::from_le_bytes(prefix), file_len)?;
    let header = buf.get(8..8 + header_len).ok_or_else(|| too_short(path, file_len))?;
    let metadata = parse_header(path, header)?;
    let data = buf.get(8 + header_len..).ok_or_else(|| too_short(path, file_len))?;
    // Let safetensors check the layout too (offsets contiguous from 0, each tensor's byte size
    // equal to shape x dtype without overflow, data ending exactly at the end of the file); we
    // turn its terse errors into ones that say what is wrong.
    safetensors::SafeTensors::read_metadata(buf)
        .map_err(|e| layout_err(path, &metadata, data.len(), e))?;
    // Parsed for its checks (format, format_version, task_index) and returned beside the data.
    let meta = FileMeta::from_safetensors_map(path, metadata.metadata().as_ref())?;

    let tensor = |name: &'static str| -> Result<Raw<'_>, DataError> {
        let info = metadata.info(name).ok_or_else(|| {
            let mut present: Vec<String> = metadata.tensors().into_keys().collect();
            present.sort();
            format_err(
                path,
                format!("missing tensor `{name}` (the file has: {})", present.join(", ")),
            )
        })?;
        let (start, end) = info.data_offsets;
        let bytes = data.get(start..end).ok_or_else(|| {
            format_err(
                path,
                format!(
                    "tensor `{name}`: data_offsets [{start}, {end}] lie outside the {}-byte \
                     data section",
                    data.len()
                ),
            )
        })?;
        Ok(Raw { name, dtype: info.dtype, shape: info.shape.clone(), bytes })
    };
    let obs = tensor(OBSERVATIONS)?;
    let act = tensor(ACTIONS)?;
    let rew = tensor(REWARDS)?;
    let term = tensor(TERMINATED)?;
    let trunc = tensor(TRUNCATED)?;
    let starts = tensor(EPISODE_STARTS)?;

    expect_dtype(path, &obs, &[Dtype::F32])?;
    expect_dtype(path, &act, &[Dtype::F32])?;
    expect_dtype(path, &rew, &[Dtype::F32])?;
    // BOOL is accepted too: it is what numpy bool arrays become, and its bytes are 0/1 like U8.
    expect_dtype(path, &term, &[Dtype::U8, Dtype::BOOL])?;
    expect_dtype(path, &trunc, &[Dtype::U8, Dtype::BOOL])?;
    expect_dtype(path, &starts, &[Dtype::I64])?;

    let n = expect_rank1(path, &rew, "[N]")?;
    let obs_dim = expect_rows(path, &obs, n, "[N, obs_dim]")?;
    let act_dim = expect_rows(path, &act, n, "[N, act_dim]")?;
    for flags in [&term, &trunc] {
        let len = expect_rank1(path, flags, "[N]")?;
        if len != n {
            return Err(shape_err(
                path,
                flags.name,
                format!("[{n}] (N from `rewards`)"),
                format!("{:?}", flags.shape),
            ));
        }
    }
    let num_offsets = expect_rank1(path, &starts, "[E + 1]")?;
    if num_offsets < 2 {
        return Err(shape_err(
            path,
            EPISODE_STARTS,
            "[E + 1] with E >= 1 episodes".into(),
            format!("{:?}", starts.shape),
        ));
    }
    for flags in [&term, &trunc] {
        if let Some(i) = flags.bytes.iter().position(|&b| b > 1) {
            return Err(format_err(
                path,
                format!("`{}`[{i}] is {}; flags must be 0 or 1", flags.name, flags.bytes[i]),
            ));
        }
    }
    let offsets = decode_offsets(path, starts.bytes, n)?;

    let mut trajectories = Vec::with_capacity(offsets.len() - 1);
    for (e, w) in offsets.windows(2).enumerate() {
        let (s, t) = (w[0], w[1]);
        let traj = Trajectory {
            obs_dim,
            act_dim,
            observations: f32s(&obs.bytes[s * obs_dim * 4..t * obs_dim * 4]),
            actions: f32s(&act.bytes[s * act_dim * 4..t * act_dim * 4]),
            rewards: f32s(&rew.bytes[s * 4..t * 4]),
            terminated: term.bytes[s..t].iter().map(|&b| b == 1).collect(),
            truncated: trunc.bytes[s..t].iter().map(|&b| b == 1).collect(),
        };
        check_trajectory(e, &traj, obs_dim, act_dim)
            .map_err(|m| format_err(path, format!("{m} (episode {e} is steps {s}..{t})")))?;
        trajectories.push(traj);
    }
    let dataset = TaskDataset::new(trajectories).map_err(|e| e.in_file(path))?;
    Ok((dataset, meta))
}

fn expect_dtype(path: &Path, t: &Raw<'_>, allowed: &[Dtype]) -> Result<(), DataError> {
    if allowed.contains(&t.dtype) {
        return Ok(());
    }
    let names: Vec<String> = allowed.iter().map(|d| format!("{d:?}")).collect();
    Err(format_err(
        path,
        format!("tensor `{}` has dtype {:?}, expected {}", t.name, t.dtype, names.join(" or ")),
    ))
}

fn expect_rank1(path: &Path, t: &Raw<'_>, layout: &str) -> Result<usize, DataError> {
    match t.shape.as_slice() {
        [len] => Ok(*len),
        other => Err(shape_err(path, t.name, format!("rank 1, {layout}"), format!("{other:?}"))),
    }
}

/// `[n, d]` with `d >= 1`; returns `d`.
fn expect_rows(path: &Path, t: &Raw<'_>, n: usize, layout: &str) -> Result<usize, DataError> {
    match t.shape.as_slice() {
        [rows, d] if *rows == n && *d >= 1 => Ok(*d),
        [rows, d] if *rows == n => Err(shape_err(
            path,
            t.name,
            format!("{layout} with a dimension >= 1"),
            format!("[{rows}, {d}]"),
        )),
        other => Err(shape_err(
            path,
            t.name,
            format!("{layout} with N = {n} (from `rewards`)"),
            format!("{other:?}"),
        )),
    }
}

/// Decodes `episode_starts` and checks it: first 0, last `n`, strictly increasing.
fn decode_offsets(path: &Path, bytes: &[u8], n: usize) -> Result<Vec<usize>, DataError> {
    let raw: Vec<i64> = bytes
        .chunks_exact(8)
        .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
        .collect();
    let bad = |message: String| format_err(path, format!("`{EPISODE_STARTS}`: {message}"));
    let first = raw.first().copied().unwrap_or(0);
    if first != 0 {
        return Err(bad(format!("first offset is {first}, must be 0")));
    }
    let last = raw.last().copied().unwrap_or(0);
    if usize::try_from(last).ok() != Some(n) {
        return Err(bad(format!("last offset is {last}, must be N = {n} (the number of steps)")));
    }
    let mut out = Vec::with_capacity(raw.len());
    for (i, w) in raw.windows(2).enumerate() {
        if w[1] <= w[0] {
            return Err(bad(format!(
                "offsets must strictly increase, but entries {i} and {} are {} and {} ({})",
                i + 1,
                w[0],
                w[1],
                if w[1] == w[0] { "an empty episode" } else { "decreasing" }
            )));
        }
    }
    // Strictly increasing from 0 to n, so every entry is in 0..=n and fits in usize.
    out.extend(raw.iter().map(|&o| o as usize));
    Ok(out)
}

fn f32s(bytes: &[u8]) -> Vec<f32> {
    // Decoded per element from little-endian bytes: the data is not necessarily 4-byte aligned
    // within the map, and this is also correct on big-endian hosts. It vectorises well.
    bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

/// Explains a layout error found by `SafeTensors::read_metadata`.
fn layout_err(path: &Path, metadata: &Metadata, data_len: usize, e: SafeTensorError) -> DataError {
    let message = match e {
        SafeTensorError::InvalidOffset(name) => format!(
            "tensor `{name}`: data_offsets do not follow on from the previous tensor's (tensors \
             must tile the data section without gaps or overlaps)"
        ),
        SafeTensorError::TensorInvalidInfo => {
            let bad = metadata.tensors().into_iter().find(|(_, info)| {
                let elems = info.shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
                let want = elems.and_then(|n| n.checked_mul(info.dtype.size()));
                want != Some(info.data_offsets.1.wrapping_sub(info.data_offsets.0))
            });
            match bad {
                Some((name, info)) => format!(
                    "tensor `{name}`: dtype {:?} and shape {:?} do not match its {} data bytes",
                    info.dtype,
                    info.shape,
                    info.data_offsets.1.wrapping_sub(info.data_offsets.0)
                ),
                None => "a tensor's shape and dtype do not match its data_offsets".into(),
            }
        }
        SafeTensorError::MetadataIncompleteBuffer => {
            let end = metadata.tensors().values().map(|i| i.data_offsets.1).max().unwrap_or(0);
            format!(
                "the tensors' data_offsets end at byte {end} but the data section has {data_len} \
                 bytes ({})",
                if end > data_len { "truncated file" } else { "trailing bytes" }
            )
        }
        SafeTensorError::ValidationOverflow => {
            "a tensor's shape overflows when multiplied out".into()
        }
        other => format!("invalid safetensors file: {other}"),
    };
    format_err(path, message)
}

// ---------------------------------------------------------------------------------------------
// Dataset card
// ---------------------------------------------------------------------------------------------

/// The optional `dataset.json` of a directory of native files: what was generated, how, and
/// summary statistics. Written by data-collection code; nothing needs it to read a file.
/// Unknown keys are ignored on reading, so later versions can add fields.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetCard {
    /// Always [`CARD_FORMAT_NAME`].
    #[serde(default = "card_format_name")]
    pub format: String,
    /// Card version; currently [`FORMAT_VERSION`].
    #[serde(default = "card_format_version")]
    pub format_version: String,
    /// Environment family, e.g. `cheetah_vel`.
    pub env: String,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub tasks: Vec<CardTask>,
    /// Free-form description of how the data was made (policy checkpoints, seeds, code version,
    /// simulator version, ...).
    #[serde(default)]
    pub generator: serde_json::Value,
}

fn card_format_name() -> String {
    CARD_FORMAT_NAME.to_owned()
}

fn card_format_version() -> String {
    FORMAT_VERSION.to_owned()
}

/// One task of a [`DatasetCard`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CardTask {
    pub index: usize,
    /// The task's parameters, e.g. `{"target_velocity": 0.225}`.
    #[serde(default)]
    pub params: serde_json::Value,
    pub files: Vec<CardFile>,
}

/// One file of a [`CardTask`], with its summary statistics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CardFile {
    /// File name relative to the card's directory, e.g. `cheetah_vel-2-expert.safetensors`.
    pub name: String,
    /// e.g. `expert`, `prompt-expert`.
    pub mode: String,
    pub episodes: usize,
    pub steps: usize,
    pub returns: ReturnStats,
}

impl CardFile {
    /// Describes a dataset that was (or will be) written under `name`.
    pub fn describe(name: impl Into<String>, mode: impl Into<String>, ds: &TaskDataset) -> Self {
        Self {
            name: name.into(),
            mode: mode.into(),
            episodes: ds.trajectories.len(),
            steps: ds.num_steps(),
            returns: ReturnStats::of(&ds.returns()),
        }
    }
}

/// Undiscounted episode-return statistics (population std, like numpy's default). All zero for an
/// empty list.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReturnStats {
    pub mean: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
}

impl ReturnStats {
    pub fn of(returns: &[f64]) -> Self {
        if returns.is_empty() {
            return Self { mean: 0.0, std: 0.0, min: 0.0, max: 0.0 };
        }
        let n = returns.len() as f64;
        let mean = returns.iter().sum::<f64>() / n;
        let var = returns.iter().map(|r| (r - mean) * (r - mean)).sum::<f64>() / n;
        Self {
            mean,
            std: var.sqrt(),
            min: returns.iter().copied().fold(f64::INFINITY, f64::min),
            max: returns.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

/// Reads `dir/dataset.json`; `Ok(None)` if the directory has no card.
pub fn read_card(dir: &Path) -> Result<Option<DatasetCard>, DataError> {
    let path = dir.join(CARD_FILE_NAME);
    let text = match pdt_base::fs::read_text_limited(&path, pdt_base::fs::MAX_TEXT_BYTES) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => return Err(DataError::Io { path, source }),
    };
    let card: DatasetCard = serde_json::from_str(&text)
        .map_err(|e| format_err(&path, format!("invalid dataset card: {e}")))?;
    if card.format != CARD_FORMAT_NAME {
        return Err(format_err(
            &path,
            format!("`format` is {:?}, expected {CARD_FORMAT_NAME:?}", card.format),
        ));
    }
    if card.format_version != FORMAT_VERSION {
        return Err(format_err(
            &path,
            format!(
                "`format_version` is {:?}; this reader understands only {FORMAT_VERSION:?}",
                card.format_version
            ),
        ));
    }
    // File names are names in this directory, never paths that lead out of it.
    for f in card.tasks.iter().flat_map(|t| &t.files) {
        // Separators are refused outright: `components()` ignores a trailing `/` ("a/" reads "a").
        let mut parts = Path::new(&f.name).components();
        let plain = !f.name.contains(['/', '\\'])
            && matches!(parts.next(), Some(std::path::Component::Normal(_)))
            && parts.next().is_none();
        if !plain {
            return Err(format_err(
                &path,
                format!("file name {:?} is not a plain file name in this directory", f.name),
            ));
        }
    }
    Ok(Some(card))
}

/// Writes `dir/dataset.json` (pretty-printed, atomically like the data files).
pub fn write_card(dir: &Path, card: &DatasetCard) -> Result<(), DataError> {
    let path = dir.join(CARD_FILE_NAME);
    let mut text = serde_json::to_string_pretty(card)
        .map_err(|e| format_err(&path, format!("cannot serialise the card: {e}")))?;
    text.push('\n');
    write_atomically(&path, |tmp| fs::write(tmp, text.as_bytes()).map_err(io_err(tmp)))
}
