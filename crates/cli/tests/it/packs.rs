//! Packs (docs/packs.md) through the real binary: a run trained in a pack through the
//! solo engine is the same run trained alone, file for file; a pack stopped or killed with
//! SIGKILL and resumed ends byte-identical to one never interrupted; runs that cannot share a
//! pack are refused by name.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{action_losses, fails, ok, s, tiny_setup};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A setting of an experiment file: `(section, key, TOML value)`.
type Set<'a> = (&'a str, &'a str, &'a str);

/// The tiny experiment with `sets` (`(section, key, TOML value)`) applied, written as `name.toml`.
fn member(cfg: &Path, name: &str, sets: &[Set]) -> PathBuf {
    let mut doc: toml::Table = std::fs::read_to_string(cfg).unwrap().parse().unwrap();
    for (section, key, value) in sets {
        let v: toml::Table = format!("v = {value}").parse().unwrap();
        let table = doc.entry(*section).or_insert(toml::Value::Table(toml::Table::new()));
        table.as_table_mut().unwrap().insert((*key).into(), v["v"].clone());
    }
    let path = cfg.with_file_name(format!("{name}.toml"));
    std::fs::write(&path, toml::to_string(&doc).unwrap()).unwrap();
    path
}

/// Three runs of the point robot: different seeds, one MT-ORL and one MT-BC-Finetune (whose
/// fine-tuning draws dropout from where its last step left libtorch's generator), each
/// checkpointing after every iteration (so a kill lands between checkpoints often), with two
/// threads (so the solo engine steps them at once, one thread each).
fn three(cfg: &Path) -> Vec<PathBuf> {
    three_with(cfg, &[])
}

/// [`three`] with `extra` settings in every run.
fn three_with(cfg: &Path, extra: &[(&str, &str, &str)]) -> Vec<PathBuf> {
    let mut each = vec![
        ("train", "resume_interval", "1"),
        ("eval", "finetune_steps", "2"),
        ("run", "threads", "2"),
    ];
    each.extend_from_slice(extra);
    let sets = |name: &str, method: &str, seed: &str| {
        let mut v = each.to_vec();
        v.extend([
            ("run", "method", method),
            ("run", "seed", seed),
            ("eval", "finetune_batch", "8"),
        ]);
        member(cfg, name, &v)
    };
    vec![
        sets("a", "\"prompt-dt\"", "0"),
        sets("b", "\"mt-orl\"", "1"),
        sets("c", "\"mt-bc-finetune\"", "2"),
    ]
}

/// Every file under `dir` (relative path to contents), the wall-clock fields taken out: the
/// metrics' `time/elapsed_s` and `run.json`'s `created` (and its `pack` unless `keep_pack`);
/// the lock files left out.
fn tree(dir: &Path, keep_pack: bool) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
                continue;
            }
            let name = p.strip_prefix(dir).unwrap().to_string_lossy().into_owned();
            if name.ends_with(".lock") {
                continue;
            }
            let bytes = std::fs::read(&p).unwrap();
            let text = || String::from_utf8(bytes.clone()).unwrap();
            let file = p.file_name().unwrap().to_string_lossy().into_owned();
            let clean = if file == "metrics.jsonl" {
                let lines: Vec<String> = text()
                    .lines()
                    .map(|l| {
                        let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
                        v.as_object_mut().unwrap().remove("time/elapsed_s").unwrap();
                        v.to_string()
                    })
                    .collect();
                lines.join("\n").into_bytes()
            } else if file == "metrics.csv" {
                let t = text();
                let col = t
                    .lines()
                    .next()
                    .unwrap()
                    .split(',')
                    .position(|c| c == "time/elapsed_s")
                    .unwrap();
                let lines: Vec<String> = t
                    .lines()
                    .map(|l| {
                        let mut cells: Vec<&str> = l.split(',').collect();
                        cells.remove(col);
                        cells.join(",")
                    })
                    .collect();
                lines.join("\n").into_bytes()
            } else if file == "run.json" {
                let mut v: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
                let o = v.as_object_mut().unwrap();
                o.remove("created").unwrap();
                if !keep_pack {
                    o.remove("pack");
                }
                v.to_string().into_bytes()
            } else {
                bytes
            };
            out.insert(name, clean);
        }
    }
    out
}

fn assert_same_tree(a: &Path, b: &Path, keep_pack: bool) {
    let (ta, tb) = (tree(a, keep_pack), tree(b, keep_pack));
    assert_eq!(
        ta.keys().collect::<Vec<_>>(),
        tb.keys().collect::<Vec<_>>(),
        "{} and {} hold different files",
        a.display(),
        b.display()
    );
    for (name, bytes) in &ta {
        assert!(
            bytes == &tb[name],
            "{name} differs between {} and {}:\n{}\n---\n{}",
            a.display(),
            b.display(),
            String::from_utf8_lossy(bytes),
            String::from_utf8_lossy(&tb[name])
        );
    }
}

/// The run directories of a pack directory, by name.
fn runs_of(pack: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(pack)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    v.sort();
    v
}

fn pack_args<'a>(configs: &'a [PathBuf], out: &'a Path) -> Vec<&'a str> {
    engine_pack_args("solo", configs, out)
}

fn engine_pack_args<'a>(engine: &'a str, configs: &'a [PathBuf], out: &'a Path) -> Vec<&'a str> {
    let mut args = vec!["train", "--quiet", "--engine", engine, "--out", s(out), "--pack"];
    args.extend(configs.iter().map(|c| s(c)));
    args
}

#[test]
fn a_run_trained_in_a_solo_engine_pack_is_the_run_trained_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let configs = three(&tiny_setup(tmp.path()));
    let pack = tmp.path().join("pack");
    let msg = ok(&pack_args(&configs, &pack));
    assert!(msg.contains("run 2: finished after iteration 8"), "{msg}");
    let runs = runs_of(&pack);
    assert_eq!(runs.len(), 3);
    for run in &runs {
        let info: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
        let slot = info["pack"]["slot"].as_u64().unwrap() as usize;
        assert_eq!(info["pack"], serde_json::json!({"size": 3, "slot": slot, "engine": "solo"}));
        let name = run.file_name().unwrap().to_string_lossy().into_owned();
        let alone = tmp.path().join("alone").join(&name);
        ok(&["train", "--config", s(&configs[slot]), "--out", s(&alone), "--quiet"]);
        assert_same_tree(run, &alone, false);
        let solo = std::fs::read_to_string(alone.join("run.json")).unwrap();
        assert!(!solo.contains("pack"), "a solo run records no pack: {solo}");
    }
    // A packed run reads as any other: evaluation and report.
    let ev = ok(&["eval", "--run", s(&runs[0]), "--episodes", "1"]);
    assert!(ev.contains("average (test)"), "{ev}");
    let rep = tmp.path().join("rep");
    let table = ok(&["report", s(&pack), "--out", s(&rep)]);
    assert!(table.contains("prompt-dt") && table.contains("mt-orl"), "{table}");
}

#[test]
fn a_pack_stopped_or_killed_and_resumed_ends_as_if_never_interrupted() {
    // Both engines: the batched one is not the solo runs bit for bit, but it is itself; and the
    // batched one with the flat pack optimiser (`optim.flat = "on"`, the CUDA default), whose
    // resumed runs re-enter the flat buffers through `import`.
    for (engine, extra) in
        [("solo", None), ("batched", None), ("batched", Some(("optim", "flat", "\"on\"")))]
    {
        stopped_killed_and_resumed(engine, extra.as_slice());
    }
}

fn stopped_killed_and_resumed(engine: &str, extra: &[(&str, &str, &str)]) {
    let tmp = tempfile::tempdir().unwrap();
    let configs = three_with(&tiny_setup(tmp.path()), extra);
    let (straight, cut) = (tmp.path().join("straight"), tmp.path().join("cut"));
    ok(&engine_pack_args(engine, &configs, &straight));
    // Stopped after 3 iterations of each run, resumed, stopped again, then killed at several
    // moments (creating the directories, training, checkpointing), then resumed to the end.
    let mut first = engine_pack_args(engine, &configs, &cut);
    first.extend(["--stop-after-iterations", "3"]);
    let msg = ok(&first);
    assert!(msg.contains("stopped after iteration 3"), "{msg}");
    ok(&["train", "--resume", s(&cut), "--quiet", "--stop-after-iterations", "2"]);
    for delay_ms in [5, 60, 150, 300, 500] {
        let args: Vec<&str> = vec!["train", "--resume", s(&cut), "--quiet"];
        let mut child =
            std::process::Command::new(env!("CARGO_BIN_EXE_promptdt")).args(&args).spawn().unwrap();
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        let _ = child.kill(); // SIGKILL; it may have finished already
        child.wait().unwrap();
    }
    ok(&["train", "--resume", s(&cut), "--quiet"]);
    assert_same_tree(&straight, &cut, true);
}

#[test]
fn a_pack_killed_before_its_runs_existed_resumes_from_its_record() {
    let tmp = tempfile::tempdir().unwrap();
    let configs = three(&tiny_setup(tmp.path()));
    let (straight, cut) = (tmp.path().join("straight"), tmp.path().join("cut"));
    ok(&pack_args(&configs, &straight));
    ok(&pack_args(&configs, &cut));
    // As if killed right after pack.json: one run's directory never made, another's half made.
    let runs = runs_of(&cut);
    std::fs::remove_dir_all(&runs[0]).unwrap();
    for f in ["config.toml", "task_stats.json", "metrics.jsonl", "metrics.csv", "eval.jsonl"] {
        let _ = std::fs::remove_file(runs[1].join(f));
    }
    std::fs::remove_dir_all(runs[1].join("checkpoints")).unwrap();
    let _ = std::fs::remove_file(runs[1].join("eval.csv"));
    ok(&["train", "--resume", s(&cut), "--quiet"]);
    assert_same_tree(&straight, &cut, true);
    // Starting a pack again over it is refused: it is resumed, not overwritten.
    let e = fails(&pack_args(&configs, &cut));
    assert!(e.contains("already holds a pack") && e.contains("--resume"), "{e}");
}

#[test]
fn runs_that_cannot_share_a_pack_are_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let out = tmp.path().join("p");
    let a = member(&cfg, "a", &[]);
    let cases: [(&[Set], &str); 4] = [
        (&[("model", "hidden_size", "32"), ("run", "seed", "1")], "model.hidden_size"),
        (&[("run", "method", "\"macaw\""), ("run", "seed", "1")], "MACAW trains alone"),
        (&[("run", "device", "\"cuda\""), ("run", "seed", "1")], "run.device"),
        (&[], "two runs of the pack are prompt-dt-point_robot-seed0"),
    ];
    for (i, (sets, expect)) in cases.into_iter().enumerate() {
        let b = member(&cfg, &format!("b{i}"), sets);
        let e = fails(&pack_args(&[a.clone(), b], &out));
        assert!(e.contains(expect), "{expect}: {e}");
        assert!(!out.join("pack.json").exists(), "{expect}: nothing written");
        let _ = std::fs::remove_dir_all(&out);
    }
    // One matmul precision for the process: the runs must agree, and tf32 needs a GPU (device
    // `auto` on this machine is the CPU), refused before anything is written.
    let auto = member(&cfg, "auto", &[("run", "device", "\"auto\"")]);
    let tf32 = |name: &str, seed: &str| {
        let sets =
            [("run", "device", "\"auto\""), ("run", "matmul", "\"tf32\""), ("run", "seed", seed)];
        member(&cfg, name, &sets)
    };
    for (configs, expect) in [
        (vec![auto.clone(), tf32("t1", "1")], "must agree on run.matmul"),
        (vec![tf32("t0", "0"), tf32("t1", "1")], "matmul = tf32 needs a CUDA device"),
    ] {
        let e = fails(&pack_args(&configs, &out));
        assert!(e.contains(expect), "{expect}: {e}");
        assert!(!out.join("pack.json").exists(), "{expect}: nothing written");
        let _ = std::fs::remove_dir_all(&out);
    }
    let e = fails(&["train", "--config", s(&a), "--matmul", "tf32", "--out", s(&out)]);
    assert!(e.contains("matmul = tf32 needs a CUDA device"), "{e}");
    assert!(!out.exists(), "nothing written");
    let e = fails(&["train", "--pack", s(&a)]);
    assert!(e.contains("--out"), "{e}");
    let e = fails(&["train", "--config", s(&a), "--engine", "solo", "--out", s(&out)]);
    assert!(e.contains("--engine and --pack-eval are for packs"), "{e}");
    let e = fails(&["train", "--config", s(&a), "--pack-eval", "apart", "--out", s(&out)]);
    assert!(e.contains("--engine and --pack-eval are for packs"), "{e}");
    // An old script's `--pack-eval together` is accepted with a note (a pack's runs evaluate
    // apart); this pack is then refused for its own fault (one run twice).
    let mut args = vec!["train", "--engine", "solo", "--pack-eval", "together", "--out", s(&out)];
    args.extend(["--pack", s(&a), s(&a)]);
    let e = fails(&args);
    assert!(e.contains("note: --pack-eval together is no longer an option"), "{e}");
    assert!(e.contains("two runs of the pack are"), "{e}");
    assert!(!out.join("pack.json").exists(), "nothing written");
}

#[test]
fn reproduce_packs_its_runs_and_they_are_the_runs_it_trains_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tmp.path().join("packs.toml");
    std::fs::write(&m, cli::tiny_manifest("packs", "Packs", "reproduce --pack", 2)).unwrap();
    let data = tmp.path().join("data");
    let (alone, packed, emitted) =
        (tmp.path().join("alone"), tmp.path().join("packed"), tmp.path().join("emitted"));
    let run = |out: &Path, more: &[&str]| {
        let mut args = vec!["reproduce", s(&m), "--budget", "smoke", "--out", s(out)];
        args.extend(["--data-root", s(&data), "--device", "cpu"]);
        args.extend(more);
        ok(&args)
    };
    run(&alone, &["--jobs", "2"]);
    // The batched engine (the default on a GPU): the same runs within its tolerance, not bit for
    // bit.
    let batched = tmp.path().join("batched");
    run(&batched, &["--pack", "4", "--pack-engine", "batched"]);
    let record = std::fs::read_to_string(
        batched.join("packs/point_robot_prompt-dt_smoke_seed0-x4/pack.json"),
    )
    .unwrap();
    assert!(record.contains("\"engine\": \"batched\""), "{record}");
    for k in ["point_robot/prompt-dt/smoke/seed0", "point_robot/mt-orl/smoke/seed1"] {
        let losses = |root: &Path| action_losses(&root.join("runs").join(k));
        let (a, b) = (losses(&alone), losses(&batched));
        assert_eq!(a.len(), b.len(), "{k}");
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= 5e-7 * x.abs().max(1.0), "{k}: {x} alone, {y} batched");
        }
    }
    // The solo engine: the runs trained alone, file for file.
    let msg = run(&packed, &["--pack", "4", "--pack-engine", "solo"]);
    assert!(msg.contains("4 started, 0 resumed, 0 failed"), "{msg}");
    let record = packed.join("packs/point_robot_prompt-dt_smoke_seed0-x4/pack.json");
    assert!(record.is_file(), "{msg}");
    let keys = [
        "point_robot/prompt-dt/smoke/seed0",
        "point_robot/prompt-dt/smoke/seed1",
        "point_robot/mt-orl/smoke/seed0",
        "point_robot/mt-orl/smoke/seed1",
    ];
    for k in keys {
        assert_same_tree(&alone.join("runs").join(k), &packed.join("runs").join(k), false);
    }
    // A second call (the default engine: solo on the CPU) finds them finished.
    assert!(run(&packed, &["--pack", "4"]).contains("4 runs already finished"));
    // --emit jobs --pack: one job for the pack, naming its runs, which trains them all.
    run(&emitted, &["--pack", "4", "--pack-engine", "solo", "--emit", "jobs"]);
    let jobs = std::fs::read_to_string(emitted.join("jobs/packs-smoke/jobs.txt")).unwrap();
    assert_eq!(jobs.lines().count(), 1, "{jobs}");
    assert!(jobs.contains(&format!("--only '{}'", keys.join(","))) && jobs.contains("--pack"));
    let st = std::process::Command::new("sh").arg("-c").arg(jobs.trim()).status().unwrap();
    assert!(st.success(), "{jobs}");
    for k in keys {
        assert_same_tree(&alone.join("runs").join(k), &emitted.join("runs").join(k), false);
    }
}
