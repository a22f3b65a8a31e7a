//! Every way a native file can be malformed gives an error that names the file and what is wrong,
//! and no input makes the reader panic.

#![allow(clippy::unwrap_used)] // in tests a panic is the failure report

use crate::support;

use std::path::{Path, PathBuf};

use pdt_data::native::{read_file_meta, read_task_dataset, write_task_dataset, FileMeta};
use pdt_data::DataError;
use proptest::prelude::*;
use safetensors::tensor::Dtype;
use support::{replace, safetensors_bytes, sample_dataset, standard_meta, tensors_of, RawTensor};

/// Writes `bytes` to a fresh file and reads it; returns the error message (which must name the
/// file) and the error.
fn read_err(bytes: &[u8]) -> (String, DataError) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken-0-expert.safetensors");
    std::fs::write(&path, bytes).unwrap();
    let e = read_task_dataset(&path).expect_err("malformed file must not load");
    let msg = e.to_string();
    assert!(msg.contains("broken-0-expert.safetensors"), "error does not name the file: {msg}");
    (msg, e)
}

/// A valid file's tensors, modified by `f`, then read: the error message.
fn err_after(f: impl FnOnce(&mut Vec<RawTensor>)) -> String {
    let mut t = tensors_of(&sample_dataset(3, 2)); // episodes of 7, 1, 12, 5 steps: N = 25
    f(&mut t);
    read_err(&safetensors_bytes(&t, Some(standard_meta()))).0
}

fn assert_has(msg: &str, parts: &[&str]) {
    for p in parts {
        assert!(msg.contains(p), "expected {p:?} in: {msg}");
    }
}

fn valid_bytes() -> Vec<u8> {
    safetensors_bytes(&tensors_of(&sample_dataset(3, 2)), Some(standard_meta()))
}

#[test]
fn hand_built_valid_file_loads() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ok.safetensors");
    std::fs::write(&path, valid_bytes()).unwrap();
    assert_eq!(read_task_dataset(&path).unwrap(), sample_dataset(3, 2));
}

#[test]
fn wrong_dtype() {
    let msg = err_after(|t| {
        let obs = t[0].clone();
        let data = obs
            .data
            .chunks_exact(4)
            .flat_map(|c| (f32::from_le_bytes(c.try_into().unwrap()) as f64).to_le_bytes());
        replace(t, RawTensor { dtype: Dtype::F64, data: data.collect(), ..obs.clone() });
    });
    assert_has(&msg, &["`observations`", "dtype F64", "expected F32"]);

    let msg = err_after(|t| {
        replace(
            t,
            RawTensor {
                name: "episode_starts".into(),
                dtype: Dtype::I32,
                shape: vec![5],
                data: vec![0; 20],
            },
        )
    });
    assert_has(&msg, &["`episode_starts`", "dtype I32", "expected I64"]);

    let msg = err_after(|t| {
        replace(
            t,
            RawTensor {
                name: "terminated".into(),
                dtype: Dtype::I8,
                shape: vec![25],
                data: vec![0; 25],
            },
        )
    });
    assert_has(&msg, &["`terminated`", "dtype I8", "expected U8 or BOOL"]);
}

#[test]
fn shape_mismatch() {
    // actions with 24 rows while rewards has 25.
    let (msg, e) = {
        let mut t = tensors_of(&sample_dataset(3, 2));
        replace(&mut t, RawTensor::f32("actions", vec![24, 2], &[0.0; 48]));
        read_err(&safetensors_bytes(&t, Some(standard_meta())))
    };
    assert_has(&msg, &["`actions`", "[N, act_dim]", "N = 25", "[24, 2]"]);
    assert!(matches!(
        &e,
        DataError::InFile { source, .. } if matches!(**source, DataError::Shape { field: "actions", .. })
    ));

    let msg = err_after(|t| replace(t, RawTensor::f32("rewards", vec![25, 1], &[0.0; 25])));
    assert_has(&msg, &["`rewards`", "rank 1", "[25, 1]"]);

    let msg = err_after(|t| replace(t, RawTensor::f32("observations", vec![75], &[0.0; 75])));
    assert_has(&msg, &["`observations`", "[N, obs_dim]", "[75]"]);

    let msg = err_after(|t| replace(t, RawTensor::u8("truncated", &[0; 26])));
    assert_has(&msg, &["`truncated`", "[25]", "[26]"]);
}

#[test]
fn zero_width_observations() {
    let msg = err_after(|t| replace(t, RawTensor::f32("observations", vec![25, 0], &[])));
    assert_has(&msg, &["`observations`", "dimension >= 1", "[25, 0]"]);
    let msg = err_after(|t| replace(t, RawTensor::f32("actions", vec![25, 0], &[])));
    assert_has(&msg, &["`actions`", "dimension >= 1"]);
}

#[test]
fn missing_tensor() {
    let msg = err_after(|t| t.retain(|t| t.name != "rewards"));
    assert_has(&msg, &["missing tensor `rewards`", "the file has:", "observations"]);
}

#[test]
fn bad_episode_offsets() {
    let cases: [(&[i64], &[&str]); 6] = [
        (&[1, 7, 8, 20, 25], &["`episode_starts`", "first offset", "must be 0"]),
        (&[0, 7, 8, 20, 24], &["`episode_starts`", "last offset is 24", "N = 25"]),
        (&[0, 7, 8, 20, 26], &["last offset is 26"]),
        (&[0, 7, 7, 20, 25], &["strictly increase", "entries 1 and 2", "empty episode"]),
        (&[0, 9, 8, 20, 25], &["strictly increase", "decreasing"]),
        (&[0, -3, 8, 20, 25], &["strictly increase"]),
    ];
    for (starts, parts) in cases {
        let msg = err_after(|t| replace(t, RawTensor::i64("episode_starts", starts)));
        assert_has(&msg, parts);
    }
    let msg = err_after(|t| replace(t, RawTensor::i64("episode_starts", &[0])));
    assert_has(&msg, &["`episode_starts`", "E >= 1"]);
    let msg = err_after(|t| {
        replace(
            t,
            RawTensor {
                name: "episode_starts".into(),
                dtype: Dtype::I64,
                shape: vec![1, 5],
                data: vec![0; 40],
            },
        )
    });
    assert_has(&msg, &["`episode_starts`", "rank 1"]);
}

#[test]
fn empty_dataset_file() {
    let t = vec![
        RawTensor::f32("observations", vec![0, 3], &[]),
        RawTensor::f32("actions", vec![0, 2], &[]),
        RawTensor::f32("rewards", vec![0], &[]),
        RawTensor::u8("terminated", &[]),
        RawTensor::u8("truncated", &[]),
        RawTensor::i64("episode_starts", &[0]),
    ];
    let (msg, _) = read_err(&safetensors_bytes(&t, None));
    assert_has(&msg, &["`episode_starts`", "E >= 1"]);
}

#[test]
fn non_finite_values() {
    let mut ds = sample_dataset(3, 2);
    let mut obs = tensors_of(&ds).remove(0);
    // Step 10 overall = episode 2 (steps 8..20), its step 2; component 1.
    obs.data[(10 * 3 + 1) * 4..(10 * 3 + 2) * 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let msg = err_after(|t| replace(t, obs));
    assert_has(&msg, &["episode 2", "`observations` is NaN", "step 2, component 1", "steps 8..20"]);

    ds.trajectories[0].rewards[3] = f32::NEG_INFINITY;
    let rew = tensors_of(&ds).remove(2);
    let msg = err_after(|t| replace(t, rew));
    assert_has(&msg, &["episode 0", "`rewards` is -inf at step 3"]);

    let msg =
        err_after(|t| replace(t, RawTensor::f32("actions", vec![25, 2], &[f32::INFINITY; 50])));
    assert_has(&msg, &["`actions` is inf"]);
}

#[test]
fn flags_must_be_zero_or_one() {
    let mut flags = vec![0u8; 25];
    flags[24] = 2;
    let msg = err_after(|t| replace(t, RawTensor::u8("truncated", &flags)));
    assert_has(&msg, &["`truncated`[24] is 2", "0 or 1"]);
}

#[test]
fn flags_only_at_last_step_of_an_episode() {
    let mut flags = vec![0u8; 25];
    flags[10] = 1; // inside episode 2 (steps 8..20)
    let msg = err_after(|t| replace(t, RawTensor::u8("terminated", &flags)));
    assert_has(
        &msg,
        &["episode 2", "`terminated` is set at step 2 of 12", "only allowed at its last step"],
    );
    let mut flags = vec![0u8; 25];
    flags[0] = 1;
    let msg = err_after(|t| replace(t, RawTensor::u8("truncated", &flags)));
    assert_has(&msg, &["episode 0", "`truncated` is set at step 0 of 7"]);
}

#[test]
fn metadata_checks() {
    let t = tensors_of(&sample_dataset(3, 2));
    let with = |k: &str, v: &str| {
        let mut m = standard_meta();
        m.insert(k.into(), v.into());
        safetensors_bytes(&t, Some(m))
    };
    assert_has(&read_err(&with("format", "something-else")).0, &["`format`", "not a promptdt"]);
    assert_has(
        &read_err(&with("format_version", "2")).0,
        &["`format_version` is \"2\"", "only \"1\""],
    );
    assert_has(&read_err(&with("task_index", "two")).0, &["`task_index` is \"two\""]);

    // read_file_meta applies the same checks.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.safetensors");
    std::fs::write(&path, with("format_version", "2")).unwrap();
    assert!(read_file_meta(&path).unwrap_err().to_string().contains("format_version"));
}

fn written_file() -> (tempfile::TempDir, PathBuf, Vec<u8>) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.safetensors");
    write_task_dataset(&path, &sample_dataset(3, 2), &FileMeta::new("e", 1, "expert")).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    (dir, path, bytes)
}

#[test]
fn truncated_files() {
    let (_dir, _path, bytes) = written_file();
    // Cut in the data section, in the header, in the length prefix, and empty.
    let header_len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let (msg, _) = read_err(&bytes[..bytes.len() - 5]);
    assert_has(&msg, &["truncated file"]);
    let (msg, _) = read_err(&bytes[..8 + header_len / 2]);
    assert_has(&msg, &["header length prefix", "truncated file"]);
    let (msg, _) = read_err(&bytes[..5]);
    assert_has(&msg, &["5 bytes", "too short"]);
    let (msg, _) = read_err(&[]);
    assert_has(&msg, &["0 bytes", "too short"]);
    // Trailing garbage is an error too: the header must describe the whole file.
    let mut longer = bytes.clone();
    longer.extend_from_slice(&[0; 3]);
    assert_has(&read_err(&longer).0, &["trailing bytes"]);
}

#[test]
fn huge_or_hostile_headers() {
    let (_dir, _path, bytes) = written_file();
    for claimed in [u64::MAX, 1 << 40, (1 << 20) + 1] {
        let mut b = bytes.clone();
        b[..8].copy_from_slice(&claimed.to_le_bytes());
        let (msg, _) = read_err(&b);
        assert_has(&msg, &[&claimed.to_string(), "limit"]);
    }
    // A shape whose element count overflows usize, with offsets that look plausible.
    let header =
        r#"{"rewards":{"dtype":"F32","shape":[4611686018427387904,8],"data_offsets":[0,4]}}"#;
    let mut b = (header.len() as u64).to_le_bytes().to_vec();
    b.extend_from_slice(header.as_bytes());
    b.extend_from_slice(&[0; 4]);
    assert_has(&read_err(&b).0, &["overflow"]);
    // Huge shape with a small data section.
    let header = r#"{"rewards":{"dtype":"F32","shape":[1000000000000],"data_offsets":[0,4]}}"#;
    let mut b = (header.len() as u64).to_le_bytes().to_vec();
    b.extend_from_slice(header.as_bytes());
    b.extend_from_slice(&[0; 4]);
    assert_has(&read_err(&b).0, &["`rewards`", "do not match its 4 data bytes"]);
    // Offsets past the end of the data.
    let header = r#"{"rewards":{"dtype":"F32","shape":[1000],"data_offsets":[0,4000]}}"#;
    let mut b = (header.len() as u64).to_le_bytes().to_vec();
    b.extend_from_slice(header.as_bytes());
    b.extend_from_slice(&[0; 4]);
    assert_has(&read_err(&b).0, &["truncated file"]);
    // Gaps between tensors.
    let header = r#"{"a":{"dtype":"U8","shape":[1],"data_offsets":[0,1]},"b":{"dtype":"U8","shape":[1],"data_offsets":[2,3]}}"#;
    let mut b = (header.len() as u64).to_le_bytes().to_vec();
    b.extend_from_slice(header.as_bytes());
    b.extend_from_slice(&[0; 3]);
    assert_has(&read_err(&b).0, &["`b`", "data_offsets"]);
    // Not JSON, not UTF-8, unknown dtype, deeply nested JSON.
    for (header, part) in [
        (b"not json at all".to_vec(), "header is invalid"),
        (vec![0xff, 0xfe, b'{'], "not UTF-8"),
        (br#"{"x":{"dtype":"F99","shape":[1],"data_offsets":[0,1]}}"#.to_vec(), "F99"),
        ("[".repeat(10_000).into_bytes(), "header is invalid"),
    ] {
        let mut b = (header.len() as u64).to_le_bytes().to_vec();
        b.extend_from_slice(&header);
        assert_has(&read_err(&b).0, &[part]);
    }
}

#[test]
fn read_file_meta_rejects_bad_headers() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("h.safetensors");
    let mut b = u64::MAX.to_le_bytes().to_vec();
    b.extend_from_slice(b"{}");
    std::fs::write(&path, &b).unwrap();
    assert!(read_file_meta(&path).unwrap_err().to_string().contains("limit"));
    std::fs::write(&path, [1, 2]).unwrap();
    assert!(read_file_meta(&path).unwrap_err().to_string().contains("too short"));
}

#[test]
fn missing_file_is_an_io_error_naming_it() {
    let e = read_task_dataset(Path::new("/nonexistent/dir/x-0-expert.safetensors")).unwrap_err();
    assert!(matches!(e, DataError::Io { .. }));
    assert!(e.to_string().contains("/nonexistent/dir/x-0-expert.safetensors"));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]
    /// Random corruption (byte overwrites and truncation) never panics: the reader either
    /// returns an error or a dataset (a flipped mantissa bit can leave a valid file).
    #[test]
    fn corrupted_files_never_panic(
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
        cut in prop::option::of(any::<prop::sample::Index>()),
    ) {
        let mut b = valid_bytes();
        for (i, v) in edits {
            let i = i.index(b.len());
            b[i] = v;
        }
        if let Some(c) = cut {
            let c = c.index(b.len());
            b.truncate(c);
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fuzz.safetensors");
        std::fs::write(&path, &b).unwrap();
        let _ = read_task_dataset(&path);
        let _ = read_file_meta(&path);
    }

    /// Edits confined to the JSON header (the part a hostile file controls) never panic.
    #[test]
    fn corrupted_headers_never_panic(
        edits in prop::collection::vec((any::<prop::sample::Index>(), prop::sample::select(
            b"0123456789[]{},:\"-e ".to_vec())), 1..6),
    ) {
        let mut b = valid_bytes();
        let header_len = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
        for (i, v) in edits {
            let i = 8 + i.index(header_len);
            b[i] = v;
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fuzz.safetensors");
        std::fs::write(&path, &b).unwrap();
        let _ = read_task_dataset(&path);
    }
}
