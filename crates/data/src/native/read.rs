//! Reading and validating a task's safetensors file: header, layout, dtypes, shapes, offsets.

use std::fs::File;
use std::io::{Seek, SeekFrom};
use std::time::SystemTime;

use super::*;

/// Reads only the metadata of a native file (the header; the tensor data is not read).
pub fn read_file_meta(path: &Path) -> Result<FileMeta, DataError> {
    let file = open(path)?;
    let src = Source::new(path, &file)?;
    let (_, metadata) = read_header(&src)?;
    FileMeta::from_safetensors_map(path, metadata.metadata().as_ref())
}

/// Bytes read per `read` call for the float tensors: the file is decoded through buffers of this
/// size, never held in memory whole. Large enough that the calls cost nothing next to the decode.
const CHUNK_BYTES: usize = 1 << 20;

/// Reads and fully validates a native file: dtypes and shapes of every tensor, episode offsets
/// (start at 0, end at `N`, strictly increasing: no empty episode), `obs_dim, act_dim >= 1`, finite
/// floats, 0/1 flags set only at an episode's last step, and the metadata's `format` /
/// `format_version` when present. Tensors with other names are ignored.
pub fn read_task_dataset(path: &Path) -> Result<TaskDataset, DataError> {
    read_task_dataset_with_meta(path).map(|(ds, _)| ds)
}

/// [`read_task_dataset`], also returning what the file's metadata says about itself.
///
/// The file is read with ordinary `read` calls through bounded buffers, whatever its size, and
/// decoded straight into the per-episode vectors, so peak memory is the dataset plus its two flag
/// tensors (a byte per step each, read whole) and three 1 MiB buffers.
/// It is never memory-mapped: a mapped file that another process truncates while it is decoded
/// kills the reader with SIGBUS, which no check before or after the decode can prevent (the file
/// can shrink between the check and the access). A file truncated or rewritten in place while it
/// is read is refused with an error naming it: a read past its new end, or a size or modification
/// time that differs after the read from before it, says the file changed under the reader.
pub fn read_task_dataset_with_meta(path: &Path) -> Result<(TaskDataset, FileMeta), DataError> {
    let file = open(path)?;
    let src = Source::new(path, &file)?;
    let decoded = decode(&src);
    // Checked whether the decode succeeded or not: bytes from a file that changed under the read
    // may fail any check, and "the file changed" is then the message that says what happened.
    src.check_unchanged()?;
    decoded
}

/// Opens a regular file (a FIFO or device is refused before it is opened: opening a FIFO would
/// block).
fn open(path: &Path) -> Result<File, DataError> {
    Ok(pdt_base::fs::open_regular(path).map_err(io_err(path))?.0)
}

/// An open data file read at explicit offsets, with the size and modification time it had when
/// the read began.
struct Source<'a> {
    path: &'a Path,
    file: &'a File,
    len: u64,
    modified: Option<SystemTime>,
}

impl<'a> Source<'a> {
    fn new(path: &'a Path, file: &'a File) -> Result<Self, DataError> {
        // From the open file, not the path: the name may have been replaced since it was opened.
        let meta = file.metadata().map_err(io_err(path))?;
        Ok(Self { path, file, len: meta.len(), modified: meta.modified().ok() })
    }

    /// Fills `buf` from byte `offset`. A file that ends before (it was longer when the read began)
    /// is an error saying it changed, not an I/O error.
    fn read_at(&self, offset: u64, buf: &mut [u8]) -> Result<(), DataError> {
        let mut file = self.file;
        file.seek(SeekFrom::Start(offset)).map_err(io_err(self.path))?;
        match file.read_exact(buf) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Err(self.changed()),
            Err(e) => Err(io_err(self.path)(e)),
        }
    }

    /// Refuses a file whose size or modification time differs from when the read began: another
    /// process wrote it in place during the read, so the bytes read may mix old and new.
    fn check_unchanged(&self) -> Result<(), DataError> {
        let meta = self.file.metadata().map_err(io_err(self.path))?;
        if meta.len() != self.len || meta.modified().ok() != self.modified {
            return Err(self.changed());
        }
        Ok(())
    }

    fn changed(&self) -> DataError {
        let now = match self.file.metadata() {
            Ok(m) if m.len() != self.len => format!("{} bytes now", m.len()),
            Ok(_) => "the same size now, but modified".into(),
            Err(e) => format!("unreadable now: {e}"),
        };
        format_err(
            self.path,
            format!(
                "the file changed while it was being read (it was {} bytes when the read began, \
                 {now}): another process truncated or rewrote it in place. promptdt never writes \
                 a data file in place (it renames a complete new file over the old one); read it \
                 again once the other writer is done",
                self.len
            ),
        )
    }
}

/// Reads and parses the 8-byte header length and the JSON header; returns where the data section
/// starts and the parsed header.
fn read_header(src: &Source<'_>) -> Result<(u64, Metadata), DataError> {
    let path = src.path;
    if src.len < 8 {
        return Err(too_short(path, src.len));
    }
    let mut prefix = [0u8; 8];
    src.read_at(0, &mut prefix)?;
    let header_len = check_header_len(path, u64::from_le_bytes(prefix), src.len)?;
    // Bounded by MAX_HEADER_BYTES and by the file size, so this allocation is small.
    let mut header = vec![0u8; header_len];
    src.read_at(8, &mut header)?;
    Ok((8 + header_len as u64, parse_header(path, &header)?))
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

/// A tensor located in the file, not yet read.
struct Raw {
    name: &'static str,
    dtype: Dtype,
    shape: Vec<usize>,
    /// Where its bytes are in the file (absolute offset) and how many there are.
    offset: u64,
    len: usize,
}

/// Reads a whole tensor into memory: only for the flags and the episode offsets, a byte or 8
/// per step or episode, a small part of a file whose floats take 4 bytes per dimension and step.
fn read_tensor(src: &Source<'_>, t: &Raw) -> Result<Vec<u8>, DataError> {
    let mut bytes = vec![0u8; t.len];
    src.read_at(t.offset, &mut bytes)?;
    Ok(bytes)
}

/// A float tensor read in order, through a buffer of at most [`CHUNK_BYTES`].
struct FloatStream<'s, 'a> {
    src: &'s Source<'a>,
    name: &'static str,
    /// File offset of the next byte to read, and the tensor's end.
    next: u64,
    end: u64,
    buf: Vec<u8>,
    /// Bytes of `buf` already decoded.
    used: usize,
}

impl<'s, 'a> FloatStream<'s, 'a> {
    fn new(src: &'s Source<'a>, t: &Raw) -> Self {
        let end = t.offset + t.len as u64;
        Self { src, name: t.name, next: t.offset, end, buf: Vec::new(), used: 0 }
    }

    /// The next `count` floats of the tensor.
    fn take(&mut self, count: usize) -> Result<Vec<f32>, DataError> {
        let mut out = Vec::with_capacity(count);
        while out.len() < count {
            if self.used == self.buf.len() {
                // A multiple of 4 (the chunk size and the tensor's byte size are), so no float is
                // split between two reads.
                let k = (self.end - self.next).min(CHUNK_BYTES as u64) as usize;
                if k == 0 {
                    // Unreachable after the shape and offset checks; an error rather than a panic.
                    return Err(format_err(
                        self.src.path,
                        format!(
                            "tensor `{}`: the episodes need more data than it holds",
                            self.name
                        ),
                    ));
                }
                self.buf.resize(k, 0);
                self.src.read_at(self.next, &mut self.buf)?;
                self.next += k as u64;
                self.used = 0;
            }
            let k = ((count - out.len()) * 4).min(self.buf.len() - self.used);
            out.extend(f32s(&self.buf[self.used..self.used + k]));
            self.used += k;
        }
        Ok(out)
    }
}

/// Checks the layout as `SafeTensors::read_metadata` does (offsets tile the data section from 0
/// without gaps or overlaps, each tensor's byte size is shape x dtype without overflow, the data
/// end exactly at the end of the file), without the whole file in memory; its errors are
/// explained by [`layout_err`].
fn check_layout(metadata: &Metadata, data_len: u64) -> Result<(), SafeTensorError> {
    let mut tensors: Vec<_> = metadata.tensors().into_iter().collect();
    tensors.sort_by(|(a, x), (b, y)| x.data_offsets.cmp(&y.data_offsets).then_with(|| a.cmp(b)));
    let mut start = 0usize;
    for (name, info) in tensors {
        let (s, e) = info.data_offsets;
        if s != start || e < s {
            return Err(SafeTensorError::InvalidOffset(name));
        }
        start = e;
        let elems = info.shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        let bytes = elems
            .and_then(|n| n.checked_mul(info.dtype.size()))
            .ok_or(SafeTensorError::ValidationOverflow)?;
        if e - s != bytes {
            return Err(SafeTensorError::TensorInvalidInfo);
        }
    }
    if start as u64 != data_len {
        return Err(SafeTensorError::MetadataIncompleteBuffer);
    }
    Ok(())
}

fn decode(src: &Source<'_>) -> Result<(TaskDataset, FileMeta), DataError> {
    let path = src.path;
    let (data_start, metadata) = read_header(src)?;
    let data_len = src.len - data_start;
    let data_len_usize = usize::try_from(data_len).map_err(|_| {
        format_err(path, format!("the data section ({data_len} bytes) does not fit in memory"))
    })?;
    check_layout(&metadata, data_len)
        .map_err(|e| layout_err(path, &metadata, data_len_usize, e))?;
    // Parsed for its checks (format, format_version, task_index) and returned beside the data.
    let meta = FileMeta::from_safetensors_map(path, metadata.metadata().as_ref())?;

    let tensor = |name: &'static str| -> Result<Raw, DataError> {
        let info = metadata.info(name).ok_or_else(|| {
            let mut present: Vec<String> = metadata.tensors().into_keys().collect();
            present.sort();
            format_err(
                path,
                format!("missing tensor `{name}` (the file has: {})", present.join(", ")),
            )
        })?;
        let (start, end) = info.data_offsets;
        if start > end || end > data_len_usize {
            return Err(format_err(
                path,
                format!(
                    "tensor `{name}`: data_offsets [{start}, {end}] lie outside the \
                     {data_len}-byte data section"
                ),
            ));
        }
        Ok(Raw {
            name,
            dtype: info.dtype,
            shape: info.shape.clone(),
            offset: data_start + start as u64,
            len: end - start,
        })
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
    let term_bytes = read_tensor(src, &term)?;
    let trunc_bytes = read_tensor(src, &trunc)?;
    for (flags, bytes) in [(&term, &term_bytes), (&trunc, &trunc_bytes)] {
        if let Some(i) = bytes.iter().position(|&b| b > 1) {
            return Err(format_err(
                path,
                format!("`{}`[{i}] is {}; flags must be 0 or 1", flags.name, bytes[i]),
            ));
        }
    }
    let offsets = decode_offsets(path, &read_tensor(src, &starts)?, n)?;

    // The floats are read episode by episode, in file order within each tensor.
    let (mut obs, mut act, mut rew) =
        (FloatStream::new(src, &obs), FloatStream::new(src, &act), FloatStream::new(src, &rew));

    let mut trajectories = Vec::with_capacity(offsets.len() - 1);
    for (e, w) in offsets.windows(2).enumerate() {
        let (s, t) = (w[0], w[1]);
        let traj = Trajectory {
            obs_dim,
            act_dim,
            observations: obs.take((t - s) * obs_dim)?,
            actions: act.take((t - s) * act_dim)?,
            rewards: rew.take(t - s)?,
            terminated: term_bytes[s..t].iter().map(|&b| b == 1).collect(),
            truncated: trunc_bytes[s..t].iter().map(|&b| b == 1).collect(),
        };
        check_trajectory(e, &traj, obs_dim, act_dim)
            .map_err(|m| format_err(path, format!("{m} (episode {e} is steps {s}..{t})")))?;
        trajectories.push(traj);
    }
    let dataset = TaskDataset::new(trajectories).map_err(|e| e.in_file(path))?;
    Ok((dataset, meta))
}

fn expect_dtype(path: &Path, t: &Raw, allowed: &[Dtype]) -> Result<(), DataError> {
    if allowed.contains(&t.dtype) {
        return Ok(());
    }
    let names: Vec<String> = allowed.iter().map(|d| format!("{d:?}")).collect();
    Err(format_err(
        path,
        format!("tensor `{}` has dtype {:?}, expected {}", t.name, t.dtype, names.join(" or ")),
    ))
}

fn expect_rank1(path: &Path, t: &Raw, layout: &str) -> Result<usize, DataError> {
    match t.shape.as_slice() {
        [len] => Ok(*len),
        other => Err(shape_err(path, t.name, format!("rank 1, {layout}"), format!("{other:?}"))),
    }
}

/// `[n, d]` with `d >= 1`; returns `d`.
fn expect_rows(path: &Path, t: &Raw, n: usize, layout: &str) -> Result<usize, DataError> {
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
    // Decoded per element from little-endian bytes: correct on big-endian hosts too, and it
    // vectorises well.
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
