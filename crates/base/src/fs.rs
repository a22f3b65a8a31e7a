//! Files: atomic writes, bounded reads, stale temporary files, run-directory locks.
//!
//! Every error is an `std::io::Error` whose message says what was wrong; callers add the path.

use std::fs::{File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// The marker in the names of temporary files: `.{name}.tmp-{pid}-{n}`.
const TMP_MARK: &str = ".tmp-";
static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes a file through `write(temp_path)` in the same directory, fsyncs it and renames it over
/// `path`, so a crash leaves either the old file or the new one, never a torn one. The temporary
/// name is unique per process and call, and removed on every error path.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&Path) -> io::Result<()>,
) -> io::Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "not a file path"))?
        .to_string_lossy()
        .into_owned();
    if path.is_dir() {
        return Err(io::Error::new(io::ErrorKind::IsADirectory, "is a directory"));
    }
    // `Path::parent` of a bare file name is `Some("")`: the current directory.
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}{TMP_MARK}{}-{n}", std::process::id()));
    // `create_new` reserves the name rather than reusing someone else's file.
    OpenOptions::new().write(true).create_new(true).open(&tmp)?;
    let result = (|| {
        write(&tmp)?;
        OpenOptions::new().write(true).open(&tmp)?.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
        return result;
    }
    // Make the rename durable. Best effort: some platforms cannot fsync a directory.
    if let Ok(d) = File::open(&dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// [`write_atomic_with`] for bytes in memory.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, |tmp| {
        let mut f = OpenOptions::new().write(true).truncate(true).open(tmp)?;
        f.write_all(bytes)
    })
}

/// Whether `name` is a temporary file of [`write_atomic_with`] (or of the older writers, which
/// named them `.{name}.tmp.{pid}` / `.{name}.tmp-{pid}`).
pub fn is_temp_name(name: &str) -> bool {
    name.starts_with('.') && (name.contains(TMP_MARK) || name.contains(".tmp."))
}

/// Removes the temporary files a killed writer left in `dir` (not recursive). Call it only while
/// owning the directory (see [`DirLock`]), so no live writer's file is taken. Returns the names
/// removed.
pub fn remove_stale_temps(dir: &Path) -> io::Result<Vec<String>> {
    let mut removed = Vec::new();
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(removed),
        Err(e) => return Err(e),
    };
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if is_temp_name(&name) && entry.file_type()?.is_file() {
            std::fs::remove_file(entry.path())?;
            removed.push(name);
        }
    }
    removed.sort();
    Ok(removed)
}

/// Opens `path` for reading only if it is a regular file (following symlinks): a directory, FIFO,
/// socket or device is refused with a message saying which, rather than blocking or reading
/// forever.
pub fn open_regular(path: &Path) -> io::Result<(File, u64)> {
    let meta = std::fs::metadata(path)?;
    let ft = meta.file_type();
    if !ft.is_file() {
        let what = if ft.is_dir() {
            "a directory"
        } else {
            #[cfg(unix)]
            {
                use std::os::unix::fs::FileTypeExt;
                if ft.is_fifo() {
                    "a FIFO (named pipe)"
                } else if ft.is_char_device() || ft.is_block_device() {
                    "a device"
                } else if ft.is_socket() {
                    "a socket"
                } else {
                    "not a regular file"
                }
            }
            #[cfg(not(unix))]
            {
                "not a regular file"
            }
        };
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("is {what}; expected a regular file"),
        ));
    }
    Ok((File::open(path)?, meta.len()))
}

/// Reads a regular file of at most `max_bytes` (see [`open_regular`]).
pub fn read_limited(path: &Path, max_bytes: u64) -> io::Result<Vec<u8>> {
    let (f, len) = open_regular(path)?;
    if len > max_bytes {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!(
                "is {len} bytes, more than the {max_bytes} bytes allowed for this kind of file"
            ),
        ));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    // `take` guards against a file that grows while it is read.
    f.take(max_bytes + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("grew beyond the {max_bytes} bytes allowed while being read"),
        ));
    }
    Ok(bytes)
}

/// [`read_limited`] as UTF-8 text.
pub fn read_text_limited(path: &Path, max_bytes: u64) -> io::Result<String> {
    String::from_utf8(read_limited(path, max_bytes)?)
        .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, format!("is not UTF-8 text: {e}")))
}

/// Limits for the small text files users and runs hand over (configs, JSON requests, run-directory
/// metadata): far above any real one, far below what could hurt.
pub const MAX_TEXT_BYTES: u64 = 64 << 20;

/// Limit for weights, optimiser states and the tensors handed to `model forward`.
pub const MAX_TENSOR_FILE_BYTES: u64 = 8 << 30;

/// Limit for a reference pickle read into memory (the release's largest is a few hundred MB).
pub const MAX_PICKLE_BYTES: u64 = 8 << 30;

/// Exclusive ownership of a directory by one process, held until dropped: an advisory lock on
/// `dir/.lock` (`flock`), released by the kernel when the process dies, so a killed owner never
/// leaves a stale lock.
#[derive(Debug)]
pub struct DirLock {
    _file: File,
    path: PathBuf,
}

/// An advisory lock (`flock`) on the file at `path` (created if missing, never truncated), taken
/// without waiting: `Ok(None)` when another process holds it. Held until the file is dropped;
/// the kernel releases it when the process dies.
pub fn try_lock_file(path: &Path) -> io::Result<Option<File>> {
    let file = OpenOptions::new().read(true).write(true).create(true).truncate(false).open(path)?;
    match file.try_lock() {
        Ok(()) => Ok(Some(file)),
        Err(std::fs::TryLockError::WouldBlock) => Ok(None),
        Err(std::fs::TryLockError::Error(e)) => Err(e),
    }
}

impl DirLock {
    /// Takes the lock without waiting; `Err` with kind `WouldBlock` when another process holds it.
    pub fn try_acquire(dir: &Path) -> io::Result<Self> {
        let path = dir.join(".lock");
        match try_lock_file(&path)? {
            Some(file) => Ok(Self { _file: file, path }),
            None => Err(io::Error::new(
                io::ErrorKind::WouldBlock,
                "is in use by another promptdt process",
            )),
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_and_leaves_no_temp() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.json");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
        // a failing writer leaves the old file and no temporary
        let err = write_atomic_with(&p, |_| Err(io::Error::other("boom"))).unwrap_err();
        assert_eq!(err.to_string(), "boom");
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
        assert!(write_atomic(d.path(), b"x").is_err(), "a directory is not overwritten");
    }

    #[test]
    fn stale_temps_of_every_writer_generation_are_removed() {
        let d = tempfile::tempdir().unwrap();
        for n in [".step_4.safetensors.tmp.123", ".metrics.csv.tmp-9-0", ".x.tmp-1", "keep.json"] {
            std::fs::write(d.path().join(n), b"").unwrap();
        }
        let removed = remove_stale_temps(d.path()).unwrap();
        assert_eq!(removed.len(), 3, "{removed:?}");
        assert!(d.path().join("keep.json").exists());
        assert!(remove_stale_temps(&d.path().join("missing")).unwrap().is_empty());
    }

    #[test]
    fn bounded_reads_refuse_big_files_directories_and_devices() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("f");
        std::fs::write(&p, b"12345").unwrap();
        assert_eq!(read_limited(&p, 5).unwrap(), b"12345");
        let e = read_limited(&p, 4).unwrap_err().to_string();
        assert!(e.contains("5 bytes") && e.contains("4 bytes"), "{e}");
        let e = read_limited(d.path(), 10).unwrap_err().to_string();
        assert!(e.contains("directory"), "{e}");
        #[cfg(unix)]
        {
            let e = read_limited(Path::new("/dev/zero"), 10).unwrap_err().to_string();
            assert!(e.contains("device"), "{e}");
        }
    }

    #[test]
    fn a_directory_has_one_owner_until_the_lock_is_dropped() {
        let d = tempfile::tempdir().unwrap();
        let a = DirLock::try_acquire(d.path()).unwrap();
        let e = DirLock::try_acquire(d.path()).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::WouldBlock);
        drop(a);
        DirLock::try_acquire(d.path()).unwrap();
    }
}
