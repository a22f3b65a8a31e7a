//! Reading and validating a task's safetensors file: header, layout, dtypes, shapes, offsets.

use super::*;

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
