//! Writes are atomic: no temporary file is left behind, a failed write leaves the old file as it
//! was, and concurrent readers only ever see a complete file.

#![allow(clippy::unwrap_used)] // in tests a panic is the failure report

use crate::support;

use std::path::Path;

use pdt_data::native::{read_task_dataset, write_task_dataset, FileMeta};
use pdt_data::TaskDataset;
use support::{sample_dataset, traj};

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn meta() -> FileMeta {
    FileMeta::new("cheetah_vel", 0, "expert")
}

#[test]
fn write_leaves_only_the_final_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cheetah_vel-0-expert.safetensors");
    write_task_dataset(&path, &sample_dataset(4, 2), &meta()).unwrap();
    assert_eq!(names(dir.path()), vec!["cheetah_vel-0-expert.safetensors"]);
}

#[test]
fn overwrite_replaces_the_old_content() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.safetensors");
    write_task_dataset(&path, &sample_dataset(4, 2), &meta()).unwrap();
    let other = TaskDataset::new(vec![traj(4, 2, 3, 42, true, false)]).unwrap();
    write_task_dataset(&path, &other, &meta()).unwrap();
    assert_eq!(read_task_dataset(&path).unwrap(), other);
    assert_eq!(names(dir.path()), vec!["d.safetensors"]);
}

#[test]
fn writing_over_a_directory_fails_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("taken.safetensors");
    std::fs::create_dir(&target).unwrap();
    std::fs::write(target.join("inside"), b"keep me").unwrap();
    let e = write_task_dataset(&target, &sample_dataset(4, 2), &meta()).unwrap_err();
    assert!(e.to_string().contains("taken.safetensors"), "{e}");
    assert!(target.is_dir());
    assert_eq!(std::fs::read(target.join("inside")).unwrap(), b"keep me");
    assert_eq!(names(dir.path()), vec!["taken.safetensors"], "no temp file left behind");
}

#[test]
fn failed_write_keeps_the_old_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.safetensors");
    let old = sample_dataset(4, 2);
    write_task_dataset(&path, &old, &meta()).unwrap();
    let before = std::fs::read(&path).unwrap();

    let mut bad = sample_dataset(4, 2);
    bad.trajectories[3].rewards[0] = f32::NAN;
    assert!(write_task_dataset(&path, &bad, &meta()).is_err());
    assert_eq!(std::fs::read(&path).unwrap(), before);
    assert_eq!(read_task_dataset(&path).unwrap(), old);
    assert_eq!(names(dir.path()), vec!["d.safetensors"]);
}

#[test]
fn missing_destination_directory_is_an_io_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("no/such/dir/d.safetensors");
    let e = write_task_dataset(&path, &sample_dataset(4, 2), &meta()).unwrap_err();
    assert!(matches!(e, pdt_data::DataError::Io { .. }), "{e:?}");
    assert!(e.to_string().contains("no/such/dir"), "{e}");
}

#[cfg(unix)]
#[test]
fn read_only_directory_fails_and_keeps_the_old_file() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.safetensors");
    let old = sample_dataset(4, 2);
    write_task_dataset(&path, &old, &meta()).unwrap();
    let before = std::fs::read(&path).unwrap();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o555)).unwrap();
    // Root (and CAP_DAC_OVERRIDE) ignores directory permissions; then this case cannot be made.
    let probe = dir.path().join("probe");
    if std::fs::write(&probe, b"x").is_ok() {
        let _ = std::fs::remove_file(&probe);
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
        eprintln!("note: skipping the read-only directory check: this user can write anyway");
        return;
    }
    let other = TaskDataset::new(vec![traj(4, 2, 3, 42, true, false)]).unwrap();
    let result = write_task_dataset(&path, &other, &meta());
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let e = result.unwrap_err();
    assert!(matches!(e, pdt_data::DataError::Io { .. }), "{e:?}");
    assert_eq!(std::fs::read(&path).unwrap(), before);
    assert_eq!(names(dir.path()), vec!["d.safetensors"]);
}

/// Two writers keep replacing the same file while readers read it: every read sees one of the two
/// complete datasets, never a mix or a partial file.
#[test]
fn concurrent_readers_see_complete_files() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("shared.safetensors");
    let a = sample_dataset(8, 3);
    let b = TaskDataset::new(vec![traj(8, 3, 40, 5, false, true), traj(8, 3, 9, 6, true, false)])
        .unwrap();
    write_task_dataset(&path, &a, &meta()).unwrap();
    std::thread::scope(|s| {
        for ds in [&a, &b] {
            let path = &path;
            s.spawn(move || {
                for _ in 0..50 {
                    write_task_dataset(path, ds, &meta()).unwrap();
                }
            });
        }
        for _ in 0..2 {
            s.spawn(|| {
                for _ in 0..100 {
                    let got = read_task_dataset(&path).unwrap();
                    assert!(got == a || got == b);
                }
            });
        }
    });
    assert_eq!(names(dir.path()), vec!["shared.safetensors"]);
}
