//! The results registry through the real binary, on a tiny point-robot experiment (seconds):
//! `results add` archives finished runs and refuses an unfinished one and one whose configuration
//! is not its cell's; `reproduce --report-only` from an empty directory (no run directories, no
//! data, no checkpoints) reports the archived runs exactly as the original tree reports them.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{check_fails, check_ok, promptdt_in};
use std::path::Path;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

const PROVENANCE: [&str; 10] = [
    "--commit",
    "abc1234",
    "--device-name",
    "test CPU",
    "--cpu",
    "test CPU",
    "--libtorch",
    "test",
    "--shared-with",
    "2",
];

/// `promptdt results add DIRS...` of manifest `m`'s smoke budget into `reg`, with the datasets'
/// cards under `data` and the fixed provenance.
fn add_args(m: &Path, reg: &Path, data: &Path, dirs: &[&Path]) -> Vec<String> {
    let mut a: Vec<String> = vec!["results".into(), "add".into()];
    a.extend(dirs.iter().map(|d| s(d).to_string()));
    for x in ["--exp", s(m), "--budget", "smoke", "--registry", s(reg), "--data-root", s(data)] {
        a.push(x.into());
    }
    a.extend(PROVENANCE.iter().map(|x| x.to_string()));
    a
}

#[test]
fn archived_runs_report_from_an_empty_directory_and_bad_runs_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let m = root.join("reg.toml");
    std::fs::write(&m, cli::tiny_manifest("reg", "Registry", "the results registry", 1)).unwrap();
    let tree = root.join("tree");
    let run = ["reproduce", s(&m), "--budget", "smoke", "--out", s(&tree), "--jobs", "2"];
    check_ok(&run, promptdt_in(root, &run));
    let reg = root.join("reg");
    let runs = tree.join("runs");
    let data = tree.join("data");
    let add = |dirs: &[&Path]| {
        let a = add_args(&m, &reg, &data, dirs);
        let out = promptdt_in(root, &a);
        (a, out)
    };

    // An unfinished run: its commit record one iteration short.
    let short = root.join("bad/runs/point_robot/prompt-dt/smoke/seed0");
    copy_dir(&runs.join("point_robot/prompt-dt/smoke/seed0"), &short);
    let latest = short.join("checkpoints/latest.json");
    let text = std::fs::read_to_string(&latest).unwrap();
    std::fs::write(&latest, text.replace("\"iteration\": 2", "\"iteration\": 1")).unwrap();
    let (a, out) = add(&[&short]);
    let err = check_fails(&a, out);
    assert!(err.contains("unfinished: 1 of 2 iterations"), "{err}");
    // A run whose configuration is not its cell's: named by key and value.
    std::fs::write(&latest, text).unwrap();
    let config = short.join("config.toml");
    let text = std::fs::read_to_string(&config).unwrap();
    assert!(text.contains("batch_size_per_task = 1"), "{text}");
    std::fs::write(&config, text.replace("batch_size_per_task = 1", "batch_size_per_task = 3"))
        .unwrap();
    let (a, out) = add(&[&short]);
    let err = check_fails(&a, out);
    assert!(err.contains("sampler.batch_size_per_task (3 vs 1)"), "{err}");
    assert!(!reg.join("point_robot/prompt-dt/smoke/seed0").exists());

    let good = [
        runs.join("point_robot/prompt-dt/smoke/seed0"),
        runs.join("point_robot/mt-orl/smoke/seed0"),
    ];
    let (a, out) = add(&[&good[0], &good[1]]);
    let stdout = check_ok(&a, out);
    assert!(stdout.contains("archived point_robot/mt-orl/smoke/seed0"), "{stdout}");
    let archived = reg.join("point_robot/prompt-dt/smoke/seed0");
    for f in ["config.toml", "run.json", "eval.jsonl", "metrics.jsonl", "task_stats.json"] {
        assert!(archived.join(f).is_file(), "{f}");
    }
    for f in ["normalisation.json", "provenance.json", "checkpoints/latest.json"] {
        assert!(archived.join(f).is_file(), "{f}");
    }
    // No weights, no datasets.
    let ckpts: Vec<_> = std::fs::read_dir(archived.join("checkpoints")).unwrap().collect();
    assert_eq!(ckpts.len(), 1);
    let prov = std::fs::read_to_string(archived.join("provenance.json")).unwrap();
    assert!(
        prov.contains("\"commit\": \"abc1234\"") && prov.contains("\"shared_with\": 2"),
        "{prov}"
    );

    // A fresh clone: nothing but the registry.
    let empty = root.join("empty");
    std::fs::create_dir(&empty).unwrap();
    let only = ["reproduce", s(&m), "--budget", "smoke", "--report-only", "--registry", s(&reg)];
    let stdout = check_ok(&only, promptdt_in(&empty, &only));
    assert!(stdout.contains("2 runs read from the registry"), "{stdout}");
    let cells =
        |dir: &Path| std::fs::read_to_string(dir.join("reports/reg-smoke/cells.csv")).unwrap();
    let fresh = cells(&empty.join("runs/repro"));
    assert_eq!(fresh, cells(&tree), "the archived runs report as the original tree");
    let report =
        std::fs::read_to_string(empty.join("runs/repro/reports/reg-smoke/report.md")).unwrap();
    assert!(!report.contains("What could not be read"), "{report}");
    assert!(!empty.join("runs/repro/data").exists() && !empty.join("runs/repro/runs").exists());
}

/// A budget planning more seeds than are archived: `--report-only` counts the seeds still to run
/// (the plan's), not only the archived ones (a registry holding only seed 0 once cut every cell
/// to 1 seed and called it finished).
#[test]
fn report_only_counts_the_planned_seeds_not_only_the_archived_ones() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let m = root.join("reg.toml");
    std::fs::write(&m, cli::tiny_manifest("reg", "Registry", "the results registry", 2)).unwrap();
    let tree = root.join("tree");
    let only = "point_robot/prompt-dt/smoke/seed0,point_robot/mt-orl/smoke/seed0";
    let run = ["reproduce", s(&m), "--budget", "smoke", "--out", s(&tree), "--only", only];
    check_ok(&run, promptdt_in(root, &run));
    let reg = root.join("reg");
    let runs = tree.join("runs");
    let dirs = ["point_robot/prompt-dt/smoke/seed0", "point_robot/mt-orl/smoke/seed0"]
        .map(|d| runs.join(d));
    let add = add_args(&m, &reg, &tree.join("data"), &[&dirs[0], &dirs[1]]);
    check_ok(&add, promptdt_in(root, &add));

    let empty = root.join("empty");
    std::fs::create_dir(&empty).unwrap();
    let only = ["reproduce", s(&m), "--budget", "smoke", "--report-only", "--registry", s(&reg)];
    check_ok(&only, promptdt_in(&empty, &only));
    let report =
        std::fs::read_to_string(empty.join("runs/repro/reports/reg-smoke/report.md")).unwrap();
    assert_eq!(report.matches("partial: 1 of 2 seeds finished").count(), 2, "{report}");

    // `--status`: each run's state and the command that goes on, nothing written.
    let latest = runs.join("point_robot/mt-orl/smoke/seed0/checkpoints/latest.json");
    let text = std::fs::read_to_string(&latest).unwrap();
    std::fs::write(&latest, text.replace("\"iteration\": 2", "\"iteration\": 1")).unwrap();
    let status = ["reproduce", s(&m), "--budget", "smoke", "--status", "--out", s(&tree)];
    let status = [&status[..], &["--registry", s(&reg)]].concat();
    let before = std::fs::read_dir(&tree).unwrap().count();
    let stdout = check_ok(&status, promptdt_in(root, &status));
    let line = |key: &str| stdout.lines().find(|l| l.starts_with(key)).unwrap_or("").to_string();
    assert!(line("point_robot/prompt-dt/smoke/seed0").ends_with("finished, archived"), "{stdout}");
    assert!(line("point_robot/prompt-dt/smoke/seed1").ends_with("not started"), "{stdout}");
    let partial = line("point_robot/mt-orl/smoke/seed0");
    assert!(partial.contains("at iteration 2 of 2 (resumes from 1); an archived copy"), "{stdout}");
    assert!(
        stdout.contains("4 runs of reg at the smoke budget: 2 done (2 archived in")
            && stdout.contains("0 part-way, 2 not started"),
        "{stdout}"
    );
    assert!(stdout.contains(&format!("--budget smoke --out {}", s(&tree))), "{stdout}");
    assert_eq!(std::fs::read_dir(&tree).unwrap().count(), before);
    // From a fresh clone: the archived runs, nothing else.
    let fresh = ["reproduce", s(&m), "--budget", "smoke", "--status", "--registry", s(&reg)];
    let stdout = check_ok(&fresh, promptdt_in(&empty, &fresh));
    let line = |key: &str| stdout.lines().find(|l| l.starts_with(key)).unwrap_or("").to_string();
    assert!(line("point_robot/mt-orl/smoke/seed0").ends_with("archived (no run directory here)"));
    assert!(stdout.contains("2 done (2 archived"), "{stdout}");
    let bad = [&fresh[..], &["--report-only"]].concat();
    cli::check_fails(&bad, promptdt_in(&empty, &bad));
}

/// `results add --date` takes a calendar date `YYYY-MM-DD` only, and a finished run whose
/// `metrics.jsonl` lost its last line (or had it torn) is refused, naming the file and the
/// missing iteration, not archived with a curve that lacks its end.
#[test]
fn add_refuses_a_date_that_is_no_day_and_a_run_whose_metrics_lost_their_end() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let m = root.join("reg.toml");
    std::fs::write(&m, cli::tiny_manifest("reg", "Registry", "the results registry", 1)).unwrap();
    let tree = root.join("tree");
    let only = "point_robot/prompt-dt/smoke/seed0";
    let run = ["reproduce", s(&m), "--budget", "smoke", "--out", s(&tree), "--only", only];
    check_ok(&run, promptdt_in(root, &run));
    let (reg, data) = (root.join("reg"), tree.join("data"));
    let good = tree.join("runs").join(only);
    let archived = reg.join(only);

    for date in ["2026-13-45", "yesterday", "2026-02-29", "26-01-01"] {
        let mut a = add_args(&m, &reg, &data, &[&good]);
        a.extend(["--date".to_string(), date.to_string()]);
        let err = check_fails(&a, promptdt_in(root, &a));
        assert!(err.contains(&format!("--date \"{date}\"")) && err.contains("YYYY-MM-DD"), "{err}");
        assert!(!archived.exists(), "{date}: nothing archived");
    }

    // The last line gone (a copy taken before it was written): iteration 2 of 2 is missing.
    let cut = root.join("cut/runs").join(only);
    copy_dir(&good, &cut);
    let metrics = cut.join("metrics.jsonl");
    let text = std::fs::read_to_string(&metrics).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 2, "{text}");
    std::fs::write(&metrics, format!("{}\n", lines[0])).unwrap();
    let a = add_args(&m, &reg, &data, &[&cut]);
    let err = check_fails(&a, promptdt_in(root, &a));
    assert!(
        err.contains(&format!("{}: not archived", cut.display()))
            && err.contains(&format!("{} ends at iteration 1", metrics.display()))
            && err.contains("iteration 2 is missing"),
        "{err}"
    );
    // Torn in the middle of its last line: named as such too.
    std::fs::write(&metrics, format!("{}\n{}", lines[0], &lines[1][..lines[1].len() / 2])).unwrap();
    let err = check_fails(&a, promptdt_in(root, &a));
    assert!(
        err.contains("iteration 2 is missing") && err.contains("skipped a truncated last line"),
        "{err}"
    );
    assert!(!archived.exists());

    // The same run whole, with a real date: archived, the date as given.
    let mut a = add_args(&m, &reg, &data, &[&good]);
    a.extend(["--date".to_string(), "2024-02-29".to_string()]);
    check_ok(&a, promptdt_in(root, &a));
    let prov = std::fs::read_to_string(archived.join("provenance.json")).unwrap();
    assert!(prov.contains("\"date\": \"2024-02-29\""), "{prov}");
}

/// The committed registry (`results/`) copied into `dir`, with the manifests and suite files of
/// the examples beside it (the user experiments' archives record their manifest from the
/// registry's directory; their data are not needed to render).
fn committed_registry(dir: &Path) -> std::path::PathBuf {
    let reg = dir.join("results");
    copy_dir(&cli::repo("results"), &reg);
    for e in std::fs::read_dir(cli::repo("examples")).unwrap() {
        let example = e.unwrap().path();
        if !example.is_dir() {
            continue;
        }
        let to = dir.join("examples").join(example.file_name().unwrap());
        std::fs::create_dir_all(&to).unwrap();
        for f in std::fs::read_dir(&example).unwrap() {
            let f = f.unwrap().path();
            if f.extension().is_some_and(|x| x == "toml") {
                std::fs::copy(&f, to.join(f.file_name().unwrap())).unwrap();
            }
        }
    }
    reg
}

/// `promptdt results render` of `reg` into `dir/RESULTS.md` (the README left alone).
fn render_args(reg: &Path, dir: &Path) -> Vec<String> {
    let out = dir.join("RESULTS.md");
    ["results", "render", "--registry", s(reg), "--out", s(&out), "--no-readme"]
        .map(String::from)
        .to_vec()
}

/// `results render` fails, naming the run's directory, the file and why, when an archived run
/// cannot be read (a cut `eval.jsonl`, a garbage `config.toml`, a corrupt `provenance.json` or
/// `normalisation.json`, a `metrics.jsonl` without its end), and writes nothing: it once left such a run out of RESULTS.md (or showed its device as `-`)
/// without a word and exited 0.
#[test]
fn render_refuses_a_registry_with_an_unreadable_run_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let reg = committed_registry(root);
    let out = root.join("RESULTS.md");
    let a = render_args(&reg, root);
    // The committed registry, copied, renders the committed RESULTS.md.
    check_ok(&a, promptdt_in(root, &a));
    let committed = std::fs::read_to_string(cli::repo("RESULTS.md")).unwrap();
    assert!(std::fs::read_to_string(&out).unwrap() == committed, "the copy renders RESULTS.md");
    std::fs::write(&out, "kept\n").unwrap();

    let key = "cheetah_vel/prompt-dt/cpu/seed0";
    let run = reg.join(key);
    let damage = |file: &str, f: &dyn Fn(&str) -> String| {
        let path = run.join(file);
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::write(&path, f(&text)).unwrap();
        text
    };
    let restore = |file: &str, text: &str| std::fs::write(run.join(file), text).unwrap();
    // The last evaluation's last line cut in the middle (a copy taken while it was written).
    let eval = damage("eval.jsonl", &|t| t[..t.len() - 40].to_string());
    let err = check_fails(&a, promptdt_in(root, &a));
    let path = run.join("eval.jsonl");
    assert!(
        err.contains(&format!("{key}: finished, but {}", path.display()))
            && err.contains("cut short")
            && err.contains("nothing written")
            && err.contains("fig2 `cpu`"),
        "{err}"
    );
    restore("eval.jsonl", &eval);
    // A garbage config.toml.
    let config = damage("config.toml", &|_| "[[[ not toml\n".into());
    let err = check_fails(&a, promptdt_in(root, &a));
    assert!(err.contains(&run.join("config.toml").display().to_string()), "{err}");
    restore("config.toml", &config);
    // A corrupt provenance.json (it was shown as device `-`).
    let prov = damage("provenance.json", &|t| t.replace("\"device_name\"", "\"device_nom\""));
    let err = check_fails(&a, promptdt_in(root, &a));
    let path = run.join("provenance.json");
    assert!(
        err.contains(&format!("{key}: {}", path.display())) && err.contains("device_name"),
        "{err}"
    );
    restore("provenance.json", &prov);
    // A corrupt normalisation.json of one seed (the report took another seed's card unseen).
    let norm = damage("normalisation.json", &|t| t[..t.len() / 2].to_string());
    let err = check_fails(&a, promptdt_in(root, &a));
    assert!(err.contains(&format!("{key}: {}", run.join("normalisation.json").display())), "{err}");
    restore("normalisation.json", &norm);
    // The training curve without its last row (its loss curve would lack the end).
    let metrics = damage("metrics.jsonl", &|t| {
        let lines: Vec<&str> = t.lines().collect();
        format!("{}\n", lines[..lines.len() - 1].join("\n"))
    });
    let err = check_fails(&a, promptdt_in(root, &a));
    let path = run.join("metrics.jsonl");
    assert!(
        err.contains(&format!("{key}: {} ends at iteration", path.display()))
            && err.contains("iteration 500 is missing"),
        "{err}"
    );
    restore("metrics.jsonl", &metrics);
    // A run's directory that lost its provenance.json (it was skipped without a word).
    let prov = damage("provenance.json", &|t| t.to_string());
    std::fs::remove_file(run.join("provenance.json")).unwrap();
    let err = check_fails(&a, promptdt_in(root, &a));
    assert!(err.contains(&format!("{key}: no provenance.json")), "{err}");
    restore("provenance.json", &prov);
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "kept\n", "nothing written");
    check_ok(&a, promptdt_in(root, &a));
    assert!(std::fs::read_to_string(&out).unwrap() == committed);
}

/// `results render --registry DIR` with no registry at DIR (absent, or holding no archived run)
/// is refused naming DIR, and the committed RESULTS.md and README stay as they are: it once
/// wrote an empty RESULTS.md over them and exited 0.
#[test]
fn render_refuses_a_registry_that_is_not_there() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::write(root.join("RESULTS.md"), "committed\n").unwrap();
    std::fs::write(root.join("README.md"), "a\n<!-- results:begin -->\nx\n<!-- results:end -->\n")
        .unwrap();
    let before = std::fs::read_to_string(root.join("README.md")).unwrap();
    let empty = root.join("empty");
    std::fs::create_dir(&empty).unwrap();
    for (reg, why) in [("no-such-dir", "no such directory"), ("empty", "holds no archived run")] {
        // The default outputs, in the working directory: RESULTS.md and README.md.
        let a = ["results", "render", "--registry", reg];
        let err = check_fails(&a, promptdt_in(root, &a));
        assert!(err.contains(&format!("--registry {reg}: {why}")), "{err}");
        assert_eq!(std::fs::read_to_string(root.join("RESULTS.md")).unwrap(), "committed\n");
        assert_eq!(std::fs::read_to_string(root.join("README.md")).unwrap(), before);
    }
}
