//! Run directories from hostile hands: any corruption of the files a run reads back
//! (`latest.json`, `state_<N>.json`, `task_stats.json`, `config.toml`, the logs) makes `train
//! --resume` and `eval` either work or fail with an error; they never panic, and a resume that
//! works continues the same run.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test
#![allow(clippy::result_large_err)] // the library's error type, returned as is

use pdt_rundir::config::TrainConfig;
use pdt_testkit::fs::copy_dir;
use pdt_train::run::{evaluate_run, train, ResumeWith, TrainOptions};
use proptest::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

const FILES: &[&str] = &[
    "checkpoints/latest.json",
    "checkpoints/state_8.json",
    "task_stats.json",
    "config.toml",
    "metrics.jsonl",
    "eval.jsonl",
    "run.json",
];

/// A finished 4-iteration run (and its data), made once for every case.
fn finished_run() -> &'static (tempfile::TempDir, PathBuf) {
    static RUN: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    RUN.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let data = tmp.path().join("data");
        let collect = pdt_envs::collect_scripted::CollectConfig {
            episodes_per_task: 3,
            prompt_episodes: 2,
            ..pdt_envs::collect_scripted::CollectConfig::for_family(
                pdt_envs::collect_scripted::ScriptedFamily::named("point_robot").unwrap(),
            )
        };
        pdt_envs::collect_scripted::collect(&collect, &data, &mut |_, _| {}).unwrap();
        let mut c: TrainConfig = toml::from_str(
            "[sampler]\nk = 4\nbatch_size_per_task = 1\n[model]\nhidden_size = 16\nn_layer = 1\n\
             n_inner = 32\n[train]\niterations = 4\nsteps_per_iteration = 2\ntest_eval_interval = 4\n\
             train_eval_interval = 0\nsave_interval = 4\n[eval]\nepisodes = 1\n[run]\nthreads = 1\n\
             device = \"cpu\"\n",
        )
        .unwrap();
        c.data.dir = data;
        let run = tmp.path().join("run");
        run_train(Some(c), &run, false, None).unwrap();
        (tmp, run)
    })
}

fn run_train(
    cfg: Option<TrainConfig>,
    dir: &Path,
    resume: bool,
    iterations: Option<u64>,
) -> Result<pdt_train::run::TrainSummary, pdt_train::run::RunError> {
    let mut progress = |_: &pdt_train::run::Progress| {};
    let resume_with = ResumeWith { iterations, ..Default::default() };
    train(
        cfg,
        dir,
        TrainOptions {
            resume,
            resume_with,
            stop_after_iterations: None,
            progress: &mut progress,
            interrupt: Default::default(),
            envs: None,
        },
    )
}

/// Replaces the `n`-th number in `text` (if any) by `to`.
fn replace_number(text: &str, n: usize, to: &str) -> String {
    let bytes = text.as_bytes();
    let mut starts = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i].is_ascii_digit()
            && (i == 0 || !bytes[i - 1].is_ascii_alphanumeric() && bytes[i - 1] != b'_')
        {
            let s = i;
            while i < bytes.len() && (bytes[i].is_ascii_digit() || bytes[i] == b'.') {
                i += 1;
            }
            starts.push((s, i));
        } else {
            i += 1;
        }
    }
    if starts.is_empty() {
        return text.to_string();
    }
    let (s, e) = starts[n % starts.len()];
    format!("{}{}{}", &text[..s], to, &text[e..])
}

#[derive(Debug, Clone)]
enum Edit {
    Byte(prop::sample::Index, u8),
    Cut(prop::sample::Index),
    Number(usize, String),
    Delete,
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<prop::sample::Index>(), any::<u8>()).prop_map(|(i, b)| Edit::Byte(i, b)),
        any::<prop::sample::Index>().prop_map(Edit::Cut),
        (
            0usize..64,
            prop_oneof![
                Just("0".to_string()),
                Just("1".to_string()),
                Just("7".to_string()),
                Just("99999999999999999999".to_string()),
                Just("-1".to_string()),
                Just("1e308".to_string()),
                Just("4.5".to_string()),
            ]
        )
            .prop_map(|(n, v)| Edit::Number(n, v)),
        Just(Edit::Delete),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn corrupted_run_files_never_panic(file in 0..FILES.len(), edits in prop::collection::vec(edit(), 1..3)) {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
        let (_tmp, run) = finished_run();
        let work = tempfile::tempdir().unwrap();
        let dir = work.path().join("run");
        copy_dir(run, &dir).unwrap();
        let path = dir.join(FILES[file]);
        for e in &edits {
            let mut bytes = std::fs::read(&path).unwrap_or_default();
            match e {
                Edit::Byte(i, b) if !bytes.is_empty() => { let i = i.index(bytes.len()); bytes[i] = *b; }
                Edit::Cut(i) if !bytes.is_empty() => bytes.truncate(i.index(bytes.len())),
                Edit::Number(n, v) => bytes = replace_number(&String::from_utf8_lossy(&bytes), *n, v).into_bytes(),
                Edit::Delete => { let _ = std::fs::remove_file(&path); continue; }
                _ => {}
            }
            std::fs::write(&path, bytes).unwrap();
        }
        // Either outcome is fine; a panic fails the test.
        let _ = evaluate_run(&dir, Some(1), "test", None, None);
        if let Ok(s) = run_train(None, &dir, true, Some(5)) {
            prop_assert_eq!(s.iterations_done, 5);
        }
    }
}
