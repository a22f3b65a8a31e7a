//! `promptdt reproduce` output trees and processes, through the real binary, on a tiny point-robot
//! experiment (seconds): a tree copied or moved is read and resumed like the original; two
//! processes on one `--out` wait for each other's runs instead of failing them; a killed
//! `reproduce` takes its children with it and its temporary data go on the next start; counts of
//! 0 are refused; and half-written trees are reported, naming what is missing, never calling a
//! finished run partial.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli;

use cli::{check_fails, check_ok, promptdt};
use proptest::prelude::*;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// Two point-robot cells of two seeds each, at a budget of seconds, with one claim.
fn trees() -> String {
    cli::tiny_manifest("trees", "Trees", "reproduce trees", 2)
}

const KEYS: [&str; 4] = [
    "point_robot/prompt-dt/smoke/seed0",
    "point_robot/prompt-dt/smoke/seed1",
    "point_robot/mt-orl/smoke/seed0",
    "point_robot/mt-orl/smoke/seed1",
];

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Writes the manifest (with `extra` appended to the smoke budget's settings) into `dir`.
fn manifest(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// `promptdt reproduce <manifest> --budget smoke --out <out> <more>`: (success, stdout, stderr).
fn reproduce(m: &Path, out: &Path, more: &[&str]) -> std::process::Output {
    let mut args = vec!["reproduce", s(m), "--budget", "smoke", "--out", s(out), "--jobs", "2"];
    args.extend(more);
    promptdt(&args)
}

fn reproduce_ok(m: &Path, out: &Path, more: &[&str]) -> String {
    check_ok(&[s(m), s(out)], reproduce(m, out, more))
}

/// `cp -a`, the way a user copies a tree.
fn copy_tree(from: &Path, to: &Path) {
    let st = Command::new("cp").arg("-a").arg(from).arg(to).status().unwrap();
    assert!(st.success(), "cp -a {} {}", from.display(), to.display());
}

#[derive(serde::Deserialize, Debug, Clone)]
struct CellJson {
    id: String,
    status: String,
    ours: Option<StatJson>,
    ours_normalised: Option<StatJson>,
    #[serde(default)]
    problems: Vec<String>,
}

#[derive(serde::Deserialize, Debug, Clone, Copy, PartialEq)]
struct StatJson {
    mean: f64,
}

#[derive(serde::Deserialize, Debug)]
struct ClaimJson {
    verdict: String,
    detail: String,
}

#[derive(serde::Deserialize, Debug)]
struct ReportJson {
    cells: Vec<CellJson>,
    claims: Vec<ClaimJson>,
}

fn report_json(out: &Path) -> ReportJson {
    let text = std::fs::read_to_string(out.join("reports/trees-smoke/report.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// A finished tree of the tiny experiment, made once for the tests that only read it.
fn finished_tree() -> &'static (tempfile::TempDir, PathBuf, PathBuf) {
    static TREE: OnceLock<(tempfile::TempDir, PathBuf, PathBuf)> = OnceLock::new();
    TREE.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let m = manifest(tmp.path(), "trees.toml", &trees());
        let out = tmp.path().join("tree");
        let msg = reproduce_ok(&m, &out, &[]);
        assert!(msg.contains("0 runs already finished, 4 started, 0 resumed, 0 failed"), "{msg}");
        let r = report_json(&out);
        assert!(r.cells.iter().all(|c| c.status == "ran" && c.ours_normalised.is_some()), "{r:?}");
        (tmp, m, out)
    })
}

/// Issue 32, 1: a tree copied (`cp -a`) or moved (`mv`) reads as the original (every finished
/// cell `ran`, the claim measured), its finished runs are skipped, a partial run resumes on the
/// tree's own data (`--data` to `train`, which checks the fingerprints), `--data-root` rebinds a
/// tree copied without its data, and data that are not what the runs trained on are named.
/// Before the fix the data directory, recorded absolute, had to match: every cell read `partial`,
/// every claim `not measured`, and `reproduce` refused every run of the copy.
#[test]
fn a_copied_or_moved_tree_reports_and_resumes_like_the_original() {
    let tmp = tempfile::tempdir().unwrap();
    let m = manifest(tmp.path(), "trees.toml", &trees());
    let a = tmp.path().join("a");
    let msg = reproduce_ok(&m, &a, &[]);
    assert!(msg.contains("4 started"), "{msg}");
    let csv = |d: &Path| std::fs::read_to_string(d.join("reports/trees-smoke/cells.csv")).unwrap();
    let cells_a = csv(&a);

    // A copy, the original still in place: the same report, no problem named.
    let b = tmp.path().join("b");
    copy_tree(&a, &b);
    std::fs::remove_dir_all(b.join("reports")).unwrap();
    reproduce_ok(&m, &b, &["--report-only"]);
    assert_eq!(csv(&b), cells_a, "the copy's report differs");
    let rb = report_json(&b);
    assert!(rb.cells.iter().all(|c| c.status == "ran" && c.problems.is_empty()), "{rb:?}");
    assert!(rb.claims.iter().all(|c| c.verdict != "not measured"), "{:?}", rb.claims);
    let again = reproduce_ok(&m, &b, &[]);
    assert!(again.contains("4 runs already finished, 0 started, 0 resumed, 0 failed"), "{again}");

    // Moved: the data the runs recorded are gone. Finished runs read as before.
    let c = tmp.path().join("c");
    std::fs::rename(&a, &c).unwrap();
    reproduce_ok(&m, &c, &["--report-only"]);
    assert_eq!(csv(&c), cells_a, "the moved tree's report differs");
    let rc = report_json(&c);
    assert!(rc.cells.iter().all(|c| c.problems.is_empty()), "{rc:?}");

    // Moved with runs stopped halfway (a sweep of 6 iterations killed once a run has a
    // checkpoint): the next `reproduce` resumes them on the moved tree's data, and each records
    // where its data are now.
    let long =
        manifest(tmp.path(), "long.toml", &trees().replace("iterations = 2\n", "iterations = 6\n"));
    let d = tmp.path().join("d");
    let mut sweep = spawn_reproduce(&long, &d);
    let t0 = Instant::now();
    let first = d.join("runs").join(KEYS[0]).join("checkpoints/latest.json");
    while !first.is_file() {
        assert!(t0.elapsed() < Duration::from_secs(120), "no checkpoint seen");
        std::thread::sleep(Duration::from_millis(20));
    }
    let kids = children(sweep.id());
    sweep.kill().unwrap();
    sweep.wait().unwrap();
    for (kid, _) in kids {
        wait_gone(kid, "train");
    }
    let e = tmp.path().join("e");
    std::fs::rename(&d, &e).unwrap();
    let resumed = reproduce_ok(&long, &e, &[]);
    assert!(resumed.contains(", 0 failed") && !resumed.contains(" 0 resumed"), "{resumed}");
    let config = std::fs::read_to_string(e.join("runs").join(KEYS[0]).join("config.toml")).unwrap();
    assert!(config.contains(s(&e.join("data"))), "{config}");
    let re = report_json(&e);
    assert!(re.cells.iter().all(|c| c.status == "ran" && c.problems.is_empty()), "{re:?}");

    // Copied without its data: the runs are still finished; the missing card is named; and
    // `--data-root` gives the data back.
    std::fs::remove_dir_all(b.join("data")).unwrap();
    reproduce_ok(&m, &b, &["--report-only"]);
    let rb = report_json(&b);
    for cell in &rb.cells {
        assert_eq!(cell.status, "ran", "{cell:?}");
        assert!(cell.ours.is_some() && cell.ours_normalised.is_none(), "{cell:?}");
        assert!(cell.problems.iter().any(|p| p.contains("point_robot-e2")), "{cell:?}");
    }
    reproduce_ok(&m, &b, &["--report-only", "--data-root", s(&c.join("data"))]);
    assert_eq!(csv(&b), cells_a, "--data-root did not rebind the copy");

    // Data of the same name but other content: the fingerprints differ, and the report says so
    // for every run instead of normalising with the wrong card.
    let other = tmp.path().join("other");
    let collected = promptdt(&[
        "collect",
        "--env",
        "point-robot",
        "--out",
        s(&other.join("point_robot-e2")),
        "--episodes",
        "3",
        "--prompt-episodes",
        "2",
    ]);
    check_ok(&["collect"], collected);
    reproduce_ok(&m, &b, &["--report-only", "--data-root", s(&other)]);
    let rb = report_json(&b);
    for cell in &rb.cells {
        assert!(cell.status.starts_with("not read"), "{cell:?}");
        assert!(
            cell.problems.iter().any(|p| p.contains("differ from what the run trained on")),
            "{cell:?}"
        );
    }
    assert!(rb.claims.iter().all(|c| c.verdict == "not measured"), "{:?}", rb.claims);
}

/// A `reproduce` (or the test itself, standing in for another process) holding a run: the
/// run directory's `.lock`, taken with `flock` the way `train` takes it.
fn hold_lock(run: &Path) -> std::fs::File {
    std::fs::create_dir_all(run).unwrap();
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(run.join(".lock"))
        .unwrap();
    f.try_lock().unwrap();
    f
}

fn spawn_reproduce(m: &Path, out: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args(["reproduce", s(m), "--budget", "smoke", "--out", s(out), "--jobs", "2"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Issue 32, 2: a run held by another process is waited for, not failed: here a `.lock` the test
/// holds (what a second `reproduce`'s child or a `train` by hand holds); then two `reproduce`
/// processes at once on one `--out`. Both end with success and a full report, and none reports
/// the other's runs as failed. Before the fix the child of the second one stopped with `in use
/// by another promptdt process` and the sweep exited 1 without a report.
#[test]
fn two_processes_on_one_out_wait_for_each_other() {
    let tmp = tempfile::tempdir().unwrap();
    let m = manifest(tmp.path(), "trees.toml", &trees());
    let out = tmp.path().join("held");
    let held = out.join("runs").join(KEYS[1]);
    let lock = hold_lock(&held);
    let child = spawn_reproduce(&m, &out);
    // The three other runs finish; the held one waits.
    let t0 = Instant::now();
    let finished = |k: &str| out.join("runs").join(k).join("checkpoints/latest.json").is_file();
    while !(finished(KEYS[0]) && finished(KEYS[2]) && finished(KEYS[3])) {
        assert!(t0.elapsed() < Duration::from_secs(120), "the free runs did not finish");
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_secs(1));
    assert!(!finished(KEYS[1]), "a held run was run");
    drop(lock);
    let done = child.wait_with_output().unwrap();
    let stdout = check_ok(&["reproduce (held)"], done);
    assert!(
        stdout.contains("3 started, 0 resumed, 0 failed")
            || stdout.contains("4 started, 0 resumed, 0 failed"),
        "{stdout}"
    );
    assert!(
        stdout.contains("waited for 1 runs another process had (0 finished there): ")
            && stdout.contains(KEYS[1]),
        "{stdout}"
    );
    assert!(report_json(&out).cells.iter().all(|c| c.status == "ran"));

    // Two at once from nothing: each runs what the other does not hold, then waits.
    let out = tmp.path().join("two");
    let (p, q) = (spawn_reproduce(&m, &out), spawn_reproduce(&m, &out));
    let (p, q) = (p.wait_with_output().unwrap(), q.wait_with_output().unwrap());
    let (p, q) = (check_ok(&["first"], p), check_ok(&["second"], q));
    for o in [&p, &q] {
        assert!(o.contains(", 0 failed"), "{o}");
        assert!(!o.contains("in use"), "{o}");
    }
    let r = report_json(&out);
    assert!(r.cells.iter().all(|c| c.status == "ran"), "{r:?}");
    // Every run trained once, by one of them: one log of one `train`.
    for k in KEYS {
        let log =
            std::fs::read_to_string(out.join("logs").join(format!("{}.log", k.replace('/', "__"))))
                .unwrap_or_default();
        assert!(!log.contains("in use"), "{k}: {log}");
    }
}

/// The live children of `pid` with their command lines (from /proc).
fn children(pid: u32) -> Vec<(u32, String)> {
    let mut v = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Some(p) = e.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else { continue };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{p}/stat")) else { continue };
        // `pid (comm) state ppid ...`: the command may hold spaces and parentheses.
        let Some(rest) = stat.rsplit_once(") ").map(|(_, r)| r) else { continue };
        let f: Vec<&str> = rest.split(' ').collect();
        if f.len() > 1 && f[1] == pid.to_string() && f[0] != "Z" {
            let cmd = std::fs::read(format!("/proc/{p}/cmdline")).unwrap_or_default();
            v.push((p, String::from_utf8_lossy(&cmd).replace('\0', " ")));
        }
    }
    v
}

/// Whether process `pid` still runs (a zombie does not).
fn alive(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .is_ok_and(|s| s.rsplit_once(") ").is_some_and(|(_, r)| !r.starts_with('Z')))
}

fn wait_gone(pid: u32, what: &str) {
    let t0 = Instant::now();
    while alive(pid) {
        // It stops as soon as it reads the end of its pipe; the collection it was making would
        // take far longer (20000 episodes per task: about 13 s alone).
        assert!(t0.elapsed() < Duration::from_secs(5), "{what} outlived its parent");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Issue 32, 3: `reproduce` killed (SIGKILL) while it collects and while it trains: its `collect`
/// and `train` children stop with it, and the next `reproduce` on the tree removes the temporary
/// data directory the killed one left. Before the fix the children ran on and
/// `<out>/data/.<env>.tmp-<pid>` stayed forever.
#[test]
fn a_killed_reproduce_takes_its_children_and_its_temporaries_go() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("killed");
    // Enough data that the collection takes a while: kill the sweep in the middle of it.
    let slow = trees().replace("data_episodes = 2\n", "data_episodes = 20000\n");
    let m = manifest(tmp.path(), "slow.toml", &slow);
    let mut sweep = spawn_reproduce(&m, &out);
    let data = out.join("data");
    let t0 = Instant::now();
    let temp = loop {
        let kids = children(sweep.id());
        let temp = std::fs::read_dir(&data).ok().and_then(|d| {
            d.flatten()
                .map(|e| e.path())
                .find(|p| p.is_dir() && p.file_name().unwrap().to_str().unwrap().contains(".tmp-"))
        });
        if let (Some((kid, cmd)), Some(temp)) = (kids.first(), temp) {
            assert!(cmd.contains("collect"), "{cmd}");
            sweep.kill().unwrap();
            sweep.wait().unwrap();
            wait_gone(*kid, "collect");
            break temp;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "no collection seen");
        assert!(sweep.try_wait().unwrap().is_none(), "the sweep ended before it was killed");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(temp.is_dir(), "the killed collection left nothing to clean");

    // The next start (the tiny experiment, on the same tree) removes it. Kill that one while it
    // trains: its `train` child stops too.
    let m = manifest(
        tmp.path(),
        "trees.toml",
        &trees().replace("iterations = 2\n", "iterations = 400\n"),
    );
    let mut sweep = spawn_reproduce(&m, &out);
    let t0 = Instant::now();
    loop {
        if let Some((kid, cmd)) =
            children(sweep.id()).into_iter().find(|(_, c)| c.contains(" train "))
        {
            assert!(cmd.contains("--die-with-parent"), "{cmd}");
            assert!(!temp.exists(), "{} was not removed", temp.display());
            sweep.kill().unwrap();
            sweep.wait().unwrap();
            wait_gone(kid, "train");
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "no training seen");
        assert!(sweep.try_wait().unwrap().is_none(), "the sweep ended before it was killed");
        std::thread::sleep(Duration::from_millis(20));
    }
    let names: Vec<String> = std::fs::read_dir(&data)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.contains(".tmp-")), "{names:?}");
}

/// Issue 32, 4: counts of 0 (and absurd ones) are refused by name, on the command line and in a
/// manifest. Before the fix `--seeds 0` planned no run and exited 0 with an empty report.
#[test]
fn counts_of_zero_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let m = manifest(tmp.path(), "trees.toml", &trees());
    let out = tmp.path().join("zero");
    for (flag, value, expect) in [
        ("--seeds", "0", "--seeds"),
        ("--seeds", "4000000000", "--seeds"),
        ("--jobs", "0", "--jobs"),
        ("--threads", "0", "--threads"),
        ("--jobs", "100000", "--jobs"),
    ] {
        let e = check_fails(&[flag, value], reproduce(&m, &out, &[flag, value, "--report-only"]));
        assert!(e.contains(expect), "{flag} {value}: {e}");
        assert!(!out.join("reports").exists(), "{flag} {value} wrote a report");
    }
    for (key, text) in [
        ("seeds", trees().replace("seeds = 2\n", "seeds = 0\n")),
        ("data_episodes", trees().replace("data_episodes = 2\n", "data_episodes = 0\n")),
        (
            "prompt_set_episodes",
            trees().replace("prompt_set_episodes = 2\n", "prompt_set_episodes = 0\n"),
        ),
    ] {
        let bad = manifest(tmp.path(), &format!("bad-{key}.toml"), &text);
        let e = check_fails(&[key], reproduce(&bad, &out, &["--report-only"]));
        assert!(e.contains(&format!("{key} must be at least 1")), "{key}: {e}");
    }
}

/// The case the property below found: a finished run's `eval.jsonl` cut inside its last
/// evaluation (some of its test tasks' lines lost) made a cell `ran` on the mean of the tasks
/// left. It is left out and named; a running run's incomplete last evaluation is not shown.
#[test]
fn a_finished_run_with_its_last_evaluation_cut_is_named() {
    let (_keep, m, tree) = finished_tree();
    let tmp = tempfile::tempdir().unwrap();
    let copy = tmp.path().join("copy");
    copy_tree(tree, &copy);
    let eval = copy.join("runs").join(KEYS[2]).join("eval.jsonl");
    let text = std::fs::read_to_string(&eval).unwrap();
    std::fs::write(&eval, &text[..text.len() - 10]).unwrap();
    reproduce_ok(m, &copy, &["--report-only"]);
    let r = report_json(&copy);
    let cell = r.cells.iter().find(|c| c.id == "point_robot/mt-orl").unwrap();
    assert_eq!(cell.status, "ran: 1 of 2 seeds read", "{cell:?}");
    assert!(
        cell.problems.iter().any(|p| p.starts_with(KEYS[2])
            && p.contains("eval.jsonl")
            && p.contains("test tasks of iteration 2")),
        "{cell:?}"
    );
}

/// The run files a report reads or that a copy can lose, and the data's card.
const FILES: &[&str] = &[
    "config.toml",
    "checkpoints/latest.json",
    "eval.jsonl",
    "metrics.jsonl",
    "task_stats.json",
    "run.json",
    "eval.csv",
];

#[derive(Debug, Clone)]
enum Damage {
    Delete,
    Truncate(f64),
    Garbage(Vec<u8>),
}

fn damage() -> impl Strategy<Value = Damage> {
    prop_oneof![
        Just(Damage::Delete),
        (0.0..1.0_f64).prop_map(Damage::Truncate),
        proptest::collection::vec(any::<u8>(), 0..64).prop_map(Damage::Garbage),
    ]
}

fn apply(path: &Path, d: &Damage) {
    match d {
        Damage::Delete => {
            let _ = std::fs::remove_file(path);
        }
        Damage::Truncate(f) => {
            if let Ok(b) = std::fs::read(path) {
                std::fs::write(path, &b[..(b.len() as f64 * f) as usize]).unwrap();
            }
        }
        Damage::Garbage(g) => std::fs::write(path, g).unwrap(),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, failure_persistence: None, ..ProptestConfig::default() })]

    /// Issue 32, 5: a finished tree, copied or moved (a new place every case, read with its own
    /// data or with `--data-root` naming the original's), with up to one file of each run
    /// damaged (deleted, cut short, overwritten) and maybe its data's card deleted: `--report-only`
    /// never fails or panics, never calls a cell of finished runs partial, names every run it
    /// leaves out by its key, and a cell it reports as `ran` has the original's numbers.
    #[test]
    fn a_half_written_tree_is_reported_without_calling_a_finished_run_partial(
        damaged in proptest::collection::vec(proptest::option::of((0..FILES.len(), damage())), 4),
        lose_card in any::<bool>(),
        own_data in any::<bool>(),
    ) {
        let (_keep, m, tree) = finished_tree();
        let original = report_json(tree);
        let tmp = tempfile::tempdir().unwrap();
        let copy = tmp.path().join("copy");
        copy_tree(tree, &copy);
        std::fs::remove_dir_all(copy.join("reports")).unwrap();
        let mut touched: Vec<(&str, &str)> = Vec::new();
        for (key, d) in KEYS.iter().zip(&damaged) {
            if let Some((f, d)) = d {
                apply(&copy.join("runs").join(key).join(FILES[*f]), d);
                touched.push((key, FILES[*f]));
            }
        }
        if lose_card {
            std::fs::remove_file(copy.join("data/point_robot-e2/dataset.json")).unwrap();
        }
        let data_root = tree.join("data");
        let mut more = vec!["--report-only"];
        if !own_data {
            more.extend(["--data-root", s(&data_root)]);
        }
        let out = reproduce(m, &copy, &more);
        let stdout = check_ok(&["--report-only on a damaged tree"], out);
        let r = report_json(&copy);
        for cell in &r.cells {
            prop_assert!(!cell.status.starts_with("partial"), "{cell:?}\n{stdout}");
            let before = original.cells.iter().find(|c| c.id == cell.id).unwrap();
            let cell_keys: Vec<&str> = KEYS.iter().copied().filter(|k| k.starts_with(&format!("{}/", cell.id))).collect();
            let left_out: Vec<&&str> = cell_keys.iter().filter(|k| cell.problems.iter().any(|p| p.starts_with(&format!("{k}: ")))).collect();
            if cell.status == "ran" {
                prop_assert!(left_out.is_empty(), "{cell:?}");
                prop_assert_eq!(cell.ours, before.ours, "{:?}", cell);
            } else {
                // Each run left out is one that was damaged, named with what is wrong.
                prop_assert!(!left_out.is_empty(), "{cell:?}");
                for k in left_out {
                    let (_, file) = touched.iter().find(|(t, _)| *t == *k).unwrap();
                    let name = Path::new(file).file_name().unwrap().to_str().unwrap();
                    let p = cell.problems.iter().find(|p| p.starts_with(&format!("{k}: "))).unwrap();
                    prop_assert!(p.contains(name) || p.contains("another configuration"), "{p}");
                }
            }
            if lose_card && own_data && cell.ours.is_some() {
                prop_assert!(cell.problems.iter().any(|p| p.contains("dataset")), "{cell:?}");
            }
        }
        for c in &r.claims {
            prop_assert!(!c.detail.is_empty());
        }
    }
}
