//! Files for tests: whole directory trees copied, the workspace's own files found.

use std::io;
use std::path::{Path, PathBuf};

/// Copies the directory tree `from` into `to` (created if missing), files and subdirectories.
pub fn copy_dir(from: &Path, to: &Path) -> io::Result<()> {
    std::fs::create_dir_all(to)?;
    for e in std::fs::read_dir(from)? {
        let e = e?;
        let dest = to.join(e.file_name());
        if e.file_type()?.is_dir() {
            copy_dir(&e.path(), &dest)?;
        } else {
            std::fs::copy(e.path(), dest)?;
        }
    }
    Ok(())
}

/// `rel` inside the workspace's checkout (its root is two levels above this crate).
pub fn repo(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").join(rel)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn copies_nested_trees_and_finds_the_workspace() -> io::Result<()> {
        let tmp = tempfile::tempdir()?;
        let src = tmp.path().join("a");
        std::fs::create_dir_all(src.join("b/c"))?;
        std::fs::write(src.join("x.txt"), "x")?;
        std::fs::write(src.join("b/c/y.txt"), "y")?;
        copy_dir(&src, &tmp.path().join("copy"))?;
        assert_eq!(std::fs::read_to_string(tmp.path().join("copy/x.txt"))?, "x");
        assert_eq!(std::fs::read_to_string(tmp.path().join("copy/b/c/y.txt"))?, "y");
        assert!(copy_dir(&tmp.path().join("missing"), &tmp.path().join("z")).is_err());
        assert!(repo("Cargo.toml").is_file());
        Ok(())
    }
}
