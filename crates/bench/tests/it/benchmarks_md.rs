//! `BENCHMARKS.md` is generated from the benchmark records (`benchmarks/*.json`), never typed:
//! regenerated here, it must equal the committed file byte for byte (after adding or changing a
//! record: `promptdt bench render`).

use pdt_bench::record::{read_dir, render_dir};
use std::path::{Path, PathBuf};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[test]
fn committed_benchmarks_md_is_the_render_of_the_records() {
    let root = repo();
    let records = read_dir(&root.join("benchmarks")).unwrap_or_else(|e| panic!("{e}"));
    // An empty directory would render a file of only the preamble (and match an emptied file).
    assert!(records.len() >= 10, "{} records under benchmarks/", records.len());
    for (path, r) in &records {
        assert!(
            !r.commands.iter().any(|c| c.trim().is_empty()),
            "{}: an empty command",
            path.display()
        );
    }
    let md = render_dir(&root.join("benchmarks")).unwrap_or_else(|e| panic!("{e}"));
    let path = root.join("BENCHMARKS.md");
    let committed =
        std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        committed == md,
        "BENCHMARKS.md differs from what `promptdt bench render` writes from benchmarks/; run it"
    );
}

#[test]
fn a_record_that_does_not_parse_is_named() {
    let dir = std::env::temp_dir().join(format!("pdt-bench-records-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(dir.join("01-bad.json"), "{\"title\": 1}").unwrap_or_else(|e| panic!("{e}"));
    let e = render_dir(&dir).err().map(|e| e.to_string()).unwrap_or_default();
    let _ = std::fs::remove_dir_all(&dir);
    assert!(e.contains("01-bad.json") && e.contains("not a benchmark record"), "{e}");
}

/// What `promptdt bench --json-out` writes: a run's record that reads back and renders, with its
/// command and today's date, and its numbers in the table.
#[test]
fn a_bench_run_becomes_a_record_that_renders() {
    let cfg = pdt_bench::BenchConfig {
        threads: 1,
        iters: 2,
        warmup: 0,
        device: tch::Device::Cpu,
        matmul: pdt_base::device::Matmul::Fp32,
        profile: false,
        cases: vec!["infer_b1".into()],
        pytorch: None,
        pytorch_eval_script: None,
        eval_episodes: 1,
        pytorch_rl_script: None,
        pytorch_macaw_script: None,
        serve_run: None,
        serve_steps: 2,
        serve_episodes: 1,
    };
    let report = pdt_bench::run(&cfg).unwrap_or_else(|e| panic!("{e}"));
    let cmd = "promptdt bench --cases infer_b1 --iters 2".to_string();
    let record = pdt_bench::record::from_report(&report, cmd.clone(), None);
    let dir = std::env::temp_dir().join(format!("pdt-bench-record-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
    let path = dir.join("01-run.json");
    record.write(&path).unwrap_or_else(|e| panic!("{e}"));
    let back = pdt_bench::record::Record::read(&path).unwrap_or_else(|e| panic!("{e}"));
    let md = render_dir(&dir).unwrap_or_else(|e| panic!("{e}"));
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(back, record);
    assert_eq!(back.commands, vec![cmd.clone()]);
    assert_eq!(back.date.len(), 10, "{}", back.date);
    assert!(md.contains("## promptdt bench: infer_b1\n"), "{md}");
    assert!(md.contains(&format!("`{cmd}`")), "{md}");
    assert!(md.contains("| infer_b1 | "), "{md}");
}
