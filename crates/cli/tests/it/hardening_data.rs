//! Hostile data files and model weights, each through the real binary: a file truncated
//! while it is read, a file whose metadata names another task, inputs and weights that
//! `model forward` must not trust, and messages that say what is actually wrong.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{fails, ok, repo, tiny_setup};
use serde_json::{json, Map, Value};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A safetensors file as plain parts, so a test can write what no well-behaved writer would.
struct St {
    meta: Map<String, Value>,
    /// name, dtype, shape, bytes
    tensors: Vec<(String, String, Vec<usize>, Vec<u8>)>,
}

fn read_st(path: &Path) -> St {
    let bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: Map<String, Value> = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let data = &bytes[8 + n..];
    let mut meta = Map::new();
    let mut tensors = Vec::new();
    for (name, v) in header {
        if name == "__metadata__" {
            meta = v.as_object().unwrap().clone();
            continue;
        }
        let off: Vec<usize> = v["data_offsets"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as usize)
            .collect();
        let shape = v["shape"].as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as usize);
        tensors.push((
            name,
            v["dtype"].as_str().unwrap().to_string(),
            shape.collect(),
            data[off[0]..off[1]].to_vec(),
        ));
    }
    St { meta, tensors }
}

fn write_st(path: &Path, st: &St) {
    let mut header = Map::new();
    if !st.meta.is_empty() {
        header.insert("__metadata__".into(), Value::Object(st.meta.clone()));
    }
    let mut data = Vec::new();
    for (name, dtype, shape, bytes) in &st.tensors {
        let start = data.len();
        data.extend_from_slice(bytes);
        header.insert(
            name.clone(),
            json!({"dtype": dtype, "shape": shape, "data_offsets": [start, data.len()]}),
        );
    }
    let text = serde_json::to_vec(&Value::Object(header)).unwrap();
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&data);
    std::fs::write(path, out).unwrap();
}

fn golden(name: &str) -> PathBuf {
    repo(&format!("testdata/golden/{name}"))
}

/// `model forward` on the golden inputs (or `inputs`) with `weights`, expected to fail.
fn forward_fails(weights: &Path, inputs: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args =
        vec!["model", "forward", "--weights", s(weights), "--inputs", s(inputs), "--out", s(out)];
    args.extend_from_slice(extra);
    fails(&args)
}

/// The number of times `needle` occurs in `hay`.
fn count(hay: &str, needle: &str) -> usize {
    hay.matches(needle).count()
}

/// Item 1: A data file truncated by another process while `promptdt` reads it: an error naming the
/// file (or a complete read, if the read won the race), never a SIGBUS. Files of this size are read
/// into memory, so nothing is left mapped for a truncation to pull away.
#[test]
fn a_file_truncated_while_it_is_read_is_an_error_not_a_crash() {
    use std::os::unix::process::ExitStatusExt;
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("big-0-expert.safetensors");
    // About 75 MB: decoding takes long enough for the truncation to land during it.
    let (obs_dim, act_dim, episodes, len) = (64, 8, 1000, 250);
    let trajectories = (0..episodes)
        .map(|e| {
            pdt_data::Trajectory::new(
                obs_dim,
                act_dim,
                (0..len * obs_dim).map(|i| (i % 97) as f32 * 0.01).collect(),
                vec![0.5; len * act_dim],
                vec![e as f32 * 0.001; len],
                vec![false; len],
                vec![false; len],
            )
            .unwrap()
        })
        .collect();
    let ds = pdt_data::TaskDataset::new(trajectories).unwrap();
    pdt_data::native::write_task_dataset(&path, &ds, &pdt_data::native::FileMeta::default())
        .unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert!(bytes.len() > 50 << 20 && (bytes.len() as u64) < (256 << 20));
    let real = std::fs::canonicalize(&path).unwrap();
    let mut truncated_while_open = 0;
    for round in 0..5 {
        std::fs::write(&path, &bytes).unwrap(); // in place, as a foreign writer would
        let mut child = Command::new(env!("CARGO_BIN_EXE_promptdt"))
            .args(["data", "inspect", s(&path)])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Truncate the moment the reader has the file open.
        let fds = PathBuf::from(format!("/proc/{}/fd", child.id()));
        while child.try_wait().unwrap().is_none() {
            let open = std::fs::read_dir(&fds)
                .into_iter()
                .flatten()
                .flatten()
                .any(|e| std::fs::read_link(e.path()).is_ok_and(|target| target == real));
            if open {
                std::fs::OpenOptions::new().write(true).open(&path).unwrap().set_len(4096).unwrap();
                truncated_while_open += 1;
                break;
            }
        }
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.code().is_some(),
            "round {round}: promptdt was killed by signal {:?} (7 is SIGBUS):\n{stderr}",
            out.status.signal()
        );
        if !out.status.success() {
            assert!(stderr.contains("big-0-expert.safetensors"), "round {round}: {stderr}");
            assert!(!stderr.contains("panicked"), "round {round}: {stderr}");
        }
    }
    assert!(truncated_while_open > 0, "no round truncated the file while it was open");
}

/// Item 2: A file whose metadata says it holds another task's data than its name says is refused,
/// naming the file and each field that disagrees.
#[test]
fn a_file_named_for_one_task_holding_another_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let path = tmp.path().join("data/point_robot-0-expert.safetensors");
    let ds = pdt_data::native::read_task_dataset(&path).unwrap();
    let good = pdt_data::native::read_file_meta(&path).unwrap();
    let other = pdt_data::native::FileMeta::new("cheetah_vel", 5, "random");
    pdt_data::native::write_task_dataset(&path, &ds, &other).unwrap();
    let run = tmp.path().join("r");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run), "--iterations", "1"]);
    assert!(e.contains("point_robot-0-expert.safetensors"), "{e}");
    assert!(e.contains("`env` is \"cheetah_vel\" but the name says \"point_robot\""), "{e}");
    assert!(e.contains("`task_index` is 5 but the name says 0"), "{e}");
    assert!(e.contains("`mode` is \"random\" but the name says \"expert\""), "{e}");
    assert!(!run.join("checkpoints").exists(), "nothing trained");
    // one field is enough
    let one = pdt_data::native::FileMeta::new("point_robot", 3, "expert");
    pdt_data::native::write_task_dataset(&path, &ds, &one).unwrap();
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run), "--iterations", "1"]);
    assert!(e.contains("`task_index` is 3 but the name says 0") && !e.contains("`env`"), "{e}");
    // the right metadata, or none at all, trains
    pdt_data::native::write_task_dataset(&path, &ds, &good).unwrap();
    ok(&["train", "--config", s(&cfg), "--out", s(&run), "--iterations", "1", "--quiet"]);
}

/// Item 4 (data): Something under a data file's name that is not a file is named as what it is, not
/// reported as missing data.
#[test]
fn a_directory_or_symlink_loop_under_a_data_name_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let path = tmp.path().join("data/point_robot-0-expert.safetensors");
    std::fs::remove_file(&path).unwrap();
    std::fs::create_dir(&path).unwrap();
    let run = tmp.path().join("r");
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("point_robot-0-expert.safetensors") && e.contains("is a directory"), "{e}");
    assert!(!e.contains("no expert data"), "{e}");
    std::fs::remove_dir(&path).unwrap();
    std::os::unix::fs::symlink(&path, &path).unwrap();
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("point_robot-0-expert.safetensors") && e.contains("symbolic links"), "{e}");
    assert!(!e.contains("no expert data"), "{e}");
    std::fs::remove_file(&path).unwrap();
    std::os::unix::fs::symlink(tmp.path().join("gone.safetensors"), &path).unwrap();
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("a symbolic link to a file that does not exist"), "{e}");
    // In every case the path is named once.
    assert_eq!(count(&e, "point_robot-0-expert.safetensors"), 1, "{e}");
    // Really missing: that is "no expert data", naming the directory once and the names tried.
    std::fs::remove_file(&path).unwrap();
    let e = fails(&["train", "--config", s(&cfg), "--out", s(&run)]);
    assert!(e.contains("no expert data for task point_robot-0"), "{e}");
    assert!(
        e.contains("tried point_robot-0-expert.safetensors and point_robot-0-expert.pkl"),
        "{e}"
    );
    assert_eq!(count(&e, s(&tmp.path().join("data"))), 1, "the directory once: {e}");
}

/// Item 3: An attention mask must hold 0 and 1 only.
#[test]
fn model_forward_refuses_attention_masks_other_than_0_and_1() {
    let tmp = tempfile::tempdir().unwrap();
    let (w, out) = (golden("prompt_dt_state_dict.safetensors"), tmp.path().join("o.safetensors"));
    for (name, value) in [("attention_mask", 7i64), ("prompt_attention_mask", -3)] {
        let mut st = read_st(&golden("prompt_dt_inputs.safetensors"));
        let t = st.tensors.iter_mut().find(|t| t.0 == name).unwrap();
        assert_eq!(t.1, "I64");
        t.3[8 * 3..8 * 4].copy_from_slice(&value.to_le_bytes());
        let inputs = tmp.path().join(format!("{name}.safetensors"));
        write_st(&inputs, &st);
        let e = forward_fails(&w, &inputs, &out, &["--n-head", "1"]);
        assert!(e.contains(&format!("`{name}`[3] is {value}")) && e.contains("0 (padding)"), "{e}");
        assert!(!out.exists());
    }
    // the golden masks (0 and 1) run
    ok(&[
        "model",
        "forward",
        "--weights",
        s(&w),
        "--inputs",
        s(&golden("prompt_dt_inputs.safetensors")),
        "--out",
        s(&out),
        "--n-head",
        "1",
    ]);
}

/// Item 3: Architecture metadata must describe the weights it comes with.
#[test]
fn model_forward_checks_recorded_architecture_against_the_shapes() {
    let tmp = tempfile::tempdir().unwrap();
    let (i, out) = (golden("prompt_dt_inputs.safetensors"), tmp.path().join("o.safetensors"));
    let base = read_st(&golden("prompt_dt_state_dict.safetensors"));
    // the golden model: 128 wide, 3 blocks, 4 x 128 MLP, 20/6 dims, 1000 timesteps
    let arch = json!({"state_dim": 20, "act_dim": 6, "hidden_size": 128, "n_layer": 3,
        "n_head": 1, "n_inner": 512, "max_ep_len": 1000, "n_positions": 1024});
    let labelled = |edit: &dyn Fn(&mut Value)| {
        let mut a = arch.clone();
        edit(&mut a);
        let mut st = St { meta: base.meta.clone(), tensors: base.tensors.clone() };
        st.meta.insert("promptdt_architecture".into(), Value::String(a.to_string()));
        let path = tmp.path().join("w.safetensors");
        write_st(&path, &st);
        path
    };
    let e = forward_fails(&labelled(&|a| a["hidden_size"] = json!(256)), &i, &out, &[]);
    assert!(e.contains("says hidden_size = 256, but the weights have 128"), "{e}");
    assert!(e.contains("embed_state.weight"), "{e}");
    let e = forward_fails(&labelled(&|a| a["n_layer"] = json!(2)), &i, &out, &[]);
    assert!(e.contains("says n_layer = 2, but the weights have 3"), "{e}");
    let e = forward_fails(&labelled(&|a| a["max_ep_len"] = json!(10)), &i, &out, &[]);
    assert!(e.contains("says max_ep_len = 10, but the weights have 1000"), "{e}");
    let e = forward_fails(&labelled(&|a| a["state_dim"] = json!("20")), &i, &out, &[]);
    assert!(e.contains("state_dim = \"20\", expected a whole number"), "{e}");
    assert!(!out.exists());
    // a true label runs without --n-head
    let good = labelled(&|_| {});
    ok(&["model", "forward", "--weights", s(&good), "--inputs", s(&i), "--out", s(&out)]);
}

/// Item 3: Files that are not Prompt-DT weights are called that, with the names that show it,
/// instead of being asked for a number of heads.
#[test]
fn model_forward_says_when_a_file_is_not_prompt_dt_weights() {
    let tmp = tempfile::tempdir().unwrap();
    let (i, out) = (golden("prompt_dt_inputs.safetensors"), tmp.path().join("o.safetensors"));
    let e = forward_fails(&golden("macaw_f32.safetensors"), &i, &out, &[]);
    assert!(e.contains("not a Prompt-DT model: none of the 37 tensors"), "{e}");
    assert!(e.contains("(`embed_action.bias`, `embed_action.weight`"), "{e}");
    assert!(e.contains("that are not Prompt-DT's (`adapt."), "{e}");
    assert!(!e.contains("--n-head"), "{e}");
    // an optimiser state from a real run
    let cfg = tiny_setup(tmp.path());
    let run = tmp.path().join("r");
    ok(&["train", "--config", s(&cfg), "--out", s(&run), "--iterations", "1", "--quiet"]);
    let state = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| {
            p.file_name().unwrap().to_str().unwrap().starts_with("state_")
                && p.extension().is_some_and(|x| x == "safetensors")
        })
        .unwrap();
    let e = forward_fails(&state, &i, &out, &[]);
    assert!(e.contains("not a Prompt-DT model") && e.contains("that are not Prompt-DT's"), "{e}");
    assert!(!e.contains("--n-head"), "{e}");
    assert_eq!(count(&e, s(&state)), 1, "the path once: {e}");
}

/// Item 4: Half-precision weights are reported by dtype and tensor.
#[test]
fn model_forward_names_the_dtype_of_half_precision_weights() {
    let tmp = tempfile::tempdir().unwrap();
    let (i, out) = (golden("prompt_dt_inputs.safetensors"), tmp.path().join("o.safetensors"));
    let mut st = read_st(&golden("prompt_dt_state_dict.safetensors"));
    for t in &mut st.tensors {
        if t.1 == "F32" {
            // The high half of each f32 (the values do not matter: the dtype is refused).
            t.3 = t.3.chunks_exact(4).flat_map(|c| [c[2], c[3]]).collect();
            t.1 = "F16".into();
        }
    }
    let w = tmp.path().join("half.safetensors");
    write_st(&w, &st);
    let e = forward_fails(&w, &i, &out, &["--n-head", "1"]);
    assert!(e.contains("has dtype F16, expected F32"), "{e}");
    assert!(e.contains("tensor `embed_action.bias`"), "the first in name order: {e}");
    assert!(!e.contains("masked_bias"), "{e}");
}

/// Item 4: A batch of 0 is called that, not "expected [0, 20, 20]".
#[test]
fn model_forward_says_the_batch_must_not_be_empty() {
    let tmp = tempfile::tempdir().unwrap();
    let (w, out) = (golden("prompt_dt_state_dict.safetensors"), tmp.path().join("o.safetensors"));
    let mut st = read_st(&golden("prompt_dt_inputs.safetensors"));
    for t in &mut st.tensors {
        t.2[0] = 0;
        t.3.clear();
    }
    let inputs = tmp.path().join("empty.safetensors");
    write_st(&inputs, &st);
    let e = forward_fails(&w, &inputs, &out, &["--n-head", "1"]);
    assert!(e.contains("batch size") && e.contains("at least 1"), "{e}");
    assert!(!e.contains("expected [0"), "{e}");
}

/// Item 4: Files that are not safetensors at all get a plain message naming the file once, not the
/// safetensors crate's error names.
#[test]
fn model_forward_explains_broken_files_in_plain_words() {
    let tmp = tempfile::tempdir().unwrap();
    let (w, i) =
        (golden("prompt_dt_state_dict.safetensors"), golden("prompt_dt_inputs.safetensors"));
    let out = tmp.path().join("o.safetensors");
    let short = tmp.path().join("short.safetensors");
    std::fs::write(&short, b"abc").unwrap();
    let long = tmp.path().join("long.safetensors");
    std::fs::write(&long, [0xff; 64]).unwrap();
    let text = tmp.path().join("text.safetensors");
    std::fs::write(&text, b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all").unwrap();
    for (bad, says) in [
        (&short, "is 3 bytes, too short for a safetensors file"),
        (&long, "header length in the first 8 bytes"),
        (&text, "not a valid safetensors JSON header"),
    ] {
        for (weights, inputs) in [(bad, &i), (&w, bad)] {
            let e = forward_fails(weights, inputs, &out, &["--n-head", "1"]);
            assert!(e.contains(says), "{e}");
            for raw in ["HeaderTooSmall", "InvalidHeaderLength", "HeaderTooLarge", "InvalidHeader"]
            {
                assert!(!e.contains(raw), "{e}");
            }
            assert_eq!(count(&e, s(bad)), 1, "the path once: {e}");
        }
    }
    // The data readers name the file once too.
    let e = fails(&["data", "inspect", s(&short)]);
    assert_eq!(count(&e, s(&short)), 1, "the path once: {e}");
}

/// Writes a native dataset of `episodes` episodes of 250 steps (obs_dim 64, act_dim 8: 294 bytes a
/// step) straight to `path`, a part at a time, so a test can make a file of hundreds of MiB without
/// holding it in memory.
fn write_big_dataset(path: &Path, episodes: usize) {
    use std::io::Write;
    let (len, obs_dim, act_dim) = (250, 64, 8);
    let n = episodes * len;
    let le = |v: Vec<f32>| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
    let obs = le((0..len * obs_dim).map(|i| (i % 97) as f32 * 0.01).collect());
    let act = le(vec![0.5; len * act_dim]);
    let rew: Vec<u8> = (0..episodes).flat_map(|e| le(vec![e as f32 * 0.001; len])).collect();
    let starts: Vec<u8> = (0..=episodes).flat_map(|e| ((e * len) as i64).to_le_bytes()).collect();
    let tensors = [
        ("observations", "F32", vec![n, obs_dim], obs.len() * episodes),
        ("actions", "F32", vec![n, act_dim], act.len() * episodes),
        ("rewards", "F32", vec![n], rew.len()),
        ("terminated", "U8", vec![n], n),
        ("truncated", "U8", vec![n], n),
        ("episode_starts", "I64", vec![episodes + 1], starts.len()),
    ];
    let mut header = Map::new();
    let mut at = 0;
    for (name, dtype, shape, size) in tensors {
        header.insert(
            name.into(),
            json!({"dtype": dtype, "shape": shape, "data_offsets": [at, at + size]}),
        );
        at += size;
    }
    let header = serde_json::to_vec(&Value::Object(header)).unwrap();
    let mut w = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    w.write_all(&(header.len() as u64).to_le_bytes()).unwrap();
    w.write_all(&header).unwrap();
    (0..episodes).for_each(|_| w.write_all(&obs).unwrap());
    (0..episodes).for_each(|_| w.write_all(&act).unwrap());
    w.write_all(&rew).unwrap();
    w.write_all(&vec![0u8; 2 * n]).unwrap(); // terminated, truncated
    w.write_all(&starts).unwrap();
    w.flush().unwrap();
}

/// Whether process `pid` has `file` open.
fn has_open(pid: u32, file: &Path) -> bool {
    let fds = PathBuf::from(format!("/proc/{pid}/fd"));
    std::fs::read_dir(fds)
        .into_iter()
        .flatten()
        .flatten()
        .any(|e| std::fs::read_link(e.path()).is_ok_and(|target| target == file))
}

/// Issue 56, item 2: a file over 256 MiB truncated by another process while `promptdt data
/// inspect` reads it. Files that size used to be memory-mapped, and a truncation landing while the
/// map was decoded killed promptdt with SIGBUS (by hand: 5 of 5 runs that truncated the moment the
/// file was mapped). No file is mapped any more: every round ends in a complete read or in an error
/// that names the file and says it changed while it was read. The rounds truncate at delays spread
/// over the read after the file is opened, and at once if the file ever shows up mapped.
#[test]
fn a_file_over_256_mib_truncated_while_it_is_read_is_an_error_not_a_sigbus() {
    use std::os::unix::process::ExitStatusExt;
    use std::time::{Duration, Instant};
    let tmp = tempfile::tempdir().unwrap();
    let pristine = tmp.path().join("pristine");
    write_big_dataset(&pristine, 4300);
    assert!(std::fs::metadata(&pristine).unwrap().len() > 300 << 20);
    let path = tmp.path().join("big-0-expert.safetensors");
    let (mut mid_read, mut told_changed) = (0, 0);
    for round in 0..10u64 {
        // In place (the same inode, truncated and rewritten), as a foreign writer would.
        std::fs::copy(&pristine, &path).unwrap();
        let real = std::fs::canonicalize(&path).unwrap();
        let mut child = Command::new(env!("CARGO_BIN_EXE_promptdt"))
            .args(["data", "inspect", s(&path)])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let maps = PathBuf::from(format!("/proc/{}/maps", child.id()));
        let delay = Duration::from_millis(40 * round);
        let mut opened: Option<Instant> = None;
        while child.try_wait().unwrap().is_none() {
            let mapped = std::fs::read_to_string(&maps).is_ok_and(|m| m.contains("big-0-expert"));
            if opened.is_none() && has_open(child.id(), &real) {
                opened = Some(Instant::now());
            }
            if mapped || opened.is_some_and(|t| t.elapsed() >= delay) {
                std::fs::OpenOptions::new().write(true).open(&path).unwrap().set_len(4096).unwrap();
                mid_read += 1;
                break;
            }
        }
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.code().is_some(),
            "round {round}: promptdt was killed by signal {:?} (7 is SIGBUS):\n{stderr}",
            out.status.signal()
        );
        if !out.status.success() {
            assert!(stderr.contains(s(&path)) && !stderr.contains("panicked"), "{stderr}");
            // Truncated before the read began (the header says more than the file holds), or
            // during it.
            let changed = stderr.contains("the file changed while it was being read");
            assert!(changed || stderr.contains("truncated file"), "round {round}: {stderr}");
            told_changed += usize::from(changed);
        }
    }
    assert!(mid_read > 0, "no round truncated the file while it was open");
    assert!(told_changed > 0, "no round truncated the file during the read");
}

/// Issue 56, item 2: `data inspect DIR` where the data names are symbolic link loops or dangling
/// links names each of them and why, instead of saying the directory has no data files (which is
/// what it said before: the broken entries were skipped as "not files").
#[test]
fn data_inspect_names_broken_links_in_a_directory() {
    use std::os::unix::fs::symlink;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    symlink("b-0-expert.safetensors", dir.join("a-0-expert.safetensors")).unwrap();
    symlink("a-0-expert.safetensors", dir.join("b-0-expert.safetensors")).unwrap();
    symlink("gone.pkl", dir.join("c-0-expert.pkl")).unwrap();
    let e = fails(&["data", "inspect", s(dir)]);
    assert!(!e.contains("no .pkl or .safetensors files"), "{e}");
    assert!(e.contains("3 entries named as data files cannot be read"), "{e}");
    assert!(e.contains("a-0-expert.safetensors: a symbolic link to b-0-expert.safetensors"), "{e}");
    assert!(e.contains("b-0-expert.safetensors: a symbolic link to a-0-expert.safetensors"), "{e}");
    assert_eq!(count(&e, "levels of symbolic links"), 2, "{e}");
    assert!(e.contains("c-0-expert.pkl: a symbolic link to gone.pkl, which does not exist"), "{e}");
    // A good file beside them does not hide them: data inspect fails on what it cannot read.
    let good = tiny_dataset(dir);
    let e = fails(&["data", "inspect", s(dir)]);
    assert!(e.contains("3 entries named as data files cannot be read"), "{e}");
    // Broken links under other names are not data files, but when the directory holds none they
    // are named: they may be what the user meant.
    for name in ["a-0-expert.safetensors", "b-0-expert.safetensors", "c-0-expert.pkl"] {
        std::fs::remove_file(dir.join(name)).unwrap();
    }
    std::fs::remove_file(&good).unwrap();
    symlink("y", dir.join("x")).unwrap();
    symlink("x", dir.join("y")).unwrap();
    let e = fails(&["data", "inspect", s(dir)]);
    assert!(e.contains("no .pkl or .safetensors files in this directory"), "{e}");
    assert!(e.contains("x: a symbolic link to y that cannot be followed"), "{e}");
    assert!(e.contains("y: a symbolic link to x that cannot be followed"), "{e}");
    // With a data file there, the other names are left alone.
    tiny_dataset(dir);
    let shown = ok(&["data", "inspect", s(dir)]);
    assert!(shown.contains("1 file, 2 trajectories"), "{shown}");
}

/// A readable two-episode native file in `dir`; returns its path.
fn tiny_dataset(dir: &Path) -> PathBuf {
    let path = dir.join("good-0-expert.safetensors");
    let last = vec![false, false, true];
    let traj = |r: f32| {
        let (obs, act) = (vec![0.1; 6], vec![0.5; 3]);
        pdt_data::Trajectory::new(2, 1, obs, act, vec![r; 3], vec![false; 3], last.clone()).unwrap()
    };
    let ds = pdt_data::TaskDataset::new(vec![traj(1.0), traj(2.0)]).unwrap();
    pdt_data::native::write_task_dataset(&path, &ds, &pdt_data::native::FileMeta::default())
        .unwrap();
    path
}

/// Issue 56, item 2: a Dial start pose of 1e300 is refused with the number in exponent form (it
/// was printed with all its 301 digits).
#[test]
fn a_huge_dial_start_pose_is_printed_in_exponent_form() {
    let tmp = tempfile::tempdir().unwrap();
    let (init, actions) = (tmp.path().join("init.json"), tmp.path().join("actions.json"));
    std::fs::write(&init, r#"{"qpos": [1e300, 0, 0, 0, 0, 0, 0, 0, 0]}"#).unwrap();
    std::fs::write(&actions, "[[0, 0, 0, 0, 0, 0, 0, 0, 0]]").unwrap();
    let out = tmp.path().join("out.json");
    let e = fails(&[
        "env",
        "replay",
        "--env",
        "dial",
        "--task",
        "0",
        "--init",
        s(&init),
        "--actions",
        s(&actions),
        "--out",
        s(&out),
    ]);
    assert!(e.contains("initial qpos[0] is 1e300 (must be finite, at most 100 rad)"), "{e}");
    assert!(!e.contains("0000000000"), "{e}");
    assert!(e.len() < 300, "{e}");
}
