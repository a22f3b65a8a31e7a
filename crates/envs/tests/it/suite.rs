//! Task suites read from a file (`pdt_envs::suite`): a good suite is a family like the built-in
//! ones, found by `family(path)`; every bad field is refused, naming the file and the field.

#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_envs::suite::{SuiteError, SuiteFamily};
use pdt_envs::{family, EnvError, EnvFamily};
use std::path::{Path, PathBuf};

/// The toy suite the front ends' tests share (`examples/toy_line/suite.toml`: 5 goals on a line, a
/// main split and an out-of-distribution one, reference returns on task 3), with what a suite may
/// have that it leaves out added here: a success rule, a task's own target, a parameter that is an
/// array, an environment.
fn good() -> String {
    let shared = include_str!("../../../../examples/toy_line/suite.toml");
    let mut text = shared.to_string();
    for (from, to) in [
        ("prompt_length = 3\n", "prompt_length = 3\nsuccess_reward = 0.9\n"),
        ("params = { goal = 0.0 }", "params = { goal = 0.0, arm = [1.0, 0.1] }"),
        ("params = { goal = 0.25 }", "params = { goal = 0.25 }\ntarget_return = 8.0"),
    ] {
        assert!(text.contains(from), "examples/toy_line/suite.toml has no {from:?}");
        text = text.replacen(from, to, 1);
    }
    text + "\n[environment]\nentry = \"gymnasium.envs.classic_control:PendulumEnv\"\n\
            task_keyword = \"task\"\npython = \".venv/bin/python\"\n"
}

fn write(dir: &Path, text: &str) -> PathBuf {
    let path = dir.join("suite.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// The error `text` gets as a suite file, as text (checked to be a suite error).
fn error(text: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let path = write(dir.path(), text);
    let e = match family(path.to_str().unwrap()) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e,
    };
    assert!(matches!(e, EnvError::Suite(_)), "{e:?}");
    let msg = e.to_string();
    assert!(msg.contains(&path.display().to_string()), "names no file: {msg}");
    msg
}

/// [`good`] with `from` replaced by `to` (which must occur).
fn edit(from: &str, to: &str) -> String {
    let good = good();
    assert!(good.contains(from), "{from}");
    good.replacen(from, to, 1)
}

#[test]
fn a_suite_file_is_a_family() {
    let dir = tempfile::tempdir().unwrap();
    let good = good();
    let path = write(dir.path(), &good);
    let f = family(path.to_str().unwrap()).unwrap();
    assert_eq!(f.name(), "toy_line");
    assert_eq!(f.num_tasks(), 5);
    let p = f.preset();
    assert_eq!((p.obs_dim, p.act_dim, p.horizon, p.prompt_length), (2, 1, 10, 3));
    assert_eq!((p.rtg_scale, p.target_return), (10.0, 10.0));
    assert_eq!(f.action_bounds().low, vec![-1.0]);
    assert_eq!(f.action_bounds().high, vec![1.0]);
    assert_eq!(f.success_reward(), Some(0.9));
    assert_eq!(f.render_fps(), 30);
    // The declared order; no split is named `default`, so the first is the default one.
    assert_eq!(f.split_names(), vec!["main", "ood"]);
    assert_eq!(f.split("main").unwrap(), (vec![0, 1, 2], vec![3, 4]));
    assert_eq!(f.split("default").unwrap(), (vec![0, 1, 2], vec![3, 4]));
    assert_eq!(f.split("ood").unwrap(), (vec![1, 2, 3], vec![0, 4]));
    assert!(matches!(f.split("nope"), Err(EnvError::UnknownSplit { .. })));
    assert_eq!(
        f.task_params(0).unwrap(),
        serde_json::json!({"name": "g0", "params": {"goal": 0.0, "arm": [1.0, 0.1]}})
    );
    assert_eq!(f.task_target_return(1), Some(8.0));
    assert_eq!(f.task_target_return(0), None);
    assert_eq!(f.reference_returns(3), Some((9.0, 1.0)));
    assert_eq!(f.reference_returns(1), None);
    // Sizes are checked against the suite like a built-in family's.
    pdt_envs::check_dims(path.to_str().unwrap(), 2, 1).unwrap();
    assert!(matches!(
        pdt_envs::check_dims(path.to_str().unwrap(), 3, 1),
        Err(EnvError::WrongDims { .. })
    ));
    // Its environment runs in the worker, never here; the interpreter's path is the file's.
    let e = f.make(0).err().unwrap().to_string();
    assert!(e.contains("Python worker"), "{e}");
    assert!(f.make(9).is_err());
    let suite = f.as_suite().unwrap();
    assert_eq!(suite.text(), good);
    let env = suite.environment().unwrap();
    assert_eq!(env.python.as_deref(), Some(dir.path().join(".venv/bin/python").as_path()));
    assert_eq!(env.step_timeout_s, 60.0);
    assert_eq!(suite.worker_task(2).unwrap().params, serde_json::json!({"goal": 0.5}));
}

#[test]
fn without_an_environment_make_says_to_evaluate_offline() {
    let good = good();
    // The table itself: the shared file's comment says "no [environment]".
    let text = good.split("\n[environment]\n").next().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let f = SuiteFamily::load(&write(dir.path(), text)).unwrap();
    assert!(f.environment().is_none());
    let e = f.make(0).err().unwrap().to_string();
    assert!(e.contains("declares no [environment]"), "{e}");
}

#[test]
fn per_dimension_bounds_and_per_task_targets() {
    let text = edit("action_bound = 1.0", "action_low = [-1.0]\naction_high = [3.0]")
        .replace("target_return = 10.0\n", "")
        .replace("name = \"g0\"", "name = \"g0\"\ntarget_return = 11.0")
        .replace("name = \"g2\"", "name = \"g2\"\ntarget_return = 7.0")
        .replace("name = \"g3\"", "name = \"g3\"\ntarget_return = 6.5")
        .replace("name = \"g4\"", "name = \"g4\"\ntarget_return = 6.0");
    let dir = tempfile::tempdir().unwrap();
    let f = SuiteFamily::load(&write(dir.path(), &text)).unwrap();
    assert_eq!(f.action_bounds().low, vec![-1.0]);
    assert_eq!(f.action_bounds().high, vec![3.0]);
    // The largest of the tasks' targets stands for the suite (the return-token checks).
    assert_eq!(f.preset().target_return, 11.0);
    assert_eq!(f.task_target_return(4), Some(6.0));
}

#[test]
fn a_missing_field_is_named() {
    let msg = error(&edit("obs_dim = 2\n", ""));
    assert!(msg.contains("missing field `obs_dim`"), "{msg}");
    let msg = error(&edit("name = \"g2\"\n", ""));
    assert!(msg.contains("`tasks[2]`") && msg.contains("missing field `name`"), "{msg}");
    let msg = error(&edit("test = [\"g0\", \"g4\"]", ""));
    assert!(msg.contains("`splits.ood`") && msg.contains("missing field `test`"), "{msg}");
    let msg = error(&edit("action_bound = 1.0", ""));
    assert!(msg.contains("`action_bound` is missing"), "{msg}");
    let msg = error(&edit("target_return = 10.0\n", ""));
    assert!(msg.contains("`target_return` is missing") && msg.contains("tasks[0]"), "{msg}");
    let msg = error(&edit("random_return = 1.0", ""));
    assert!(msg.contains("`tasks[3].random_return` is missing"), "{msg}");
    let msg = error(&edit("entry = \"gymnasium.envs.classic_control:PendulumEnv\"", ""));
    assert!(msg.contains("`environment`") && msg.contains("missing field `entry`"), "{msg}");
}

#[test]
fn an_extra_field_is_named() {
    let msg = error(&edit("obs_dim = 2", "obs_dim = 2\nobs_size = 3"));
    assert!(msg.contains("unknown field `obs_size`"), "{msg}");
    let msg = error(&edit("params = { goal = 0.25 }", "params = { goal = 0.25 }\nweight = 2"));
    assert!(msg.contains("`tasks[1]`") && msg.contains("unknown field `weight`"), "{msg}");
    let msg = error(&edit("test = [\"g3\", \"g4\"]", "test = [\"g3\", \"g4\"]\nvalid = [\"g3\"]"));
    assert!(msg.contains("`splits.main`") && msg.contains("unknown field `valid`"), "{msg}");
    let msg = error(&edit("task_keyword = \"task\"", "task_keyword = \"task\"\ntimeout = 3"));
    assert!(msg.contains("`environment`") && msg.contains("unknown field `timeout`"), "{msg}");
}

#[test]
fn a_contradictory_field_is_named() {
    let cases: &[(&str, &str, &str)] = &[
        (
            "action_bound = 1.0",
            "action_bound = 1.0\naction_low = [-1.0]\naction_high = [1.0]",
            "`action_bound` is given together",
        ),
        (
            "action_bound = 1.0",
            "action_low = [1.0]\naction_high = [1.0]",
            "`action_low[0]` is 1, not below action_high[0]",
        ),
        (
            "action_bound = 1.0",
            "action_low = [-1.0, -1.0]\naction_high = [1.0, 1.0]",
            "`action_low` has 2 values; act_dim is 1",
        ),
        (
            "test = [\"g3\", \"g4\"]",
            "test = [\"g3\", \"g4\", \"g0\"]",
            "`splits.main.test[2]` \"g0\" is also in splits.main.train",
        ),
        (
            "test = [\"g0\", \"g4\"]",
            "test = [\"g0\", \"g4\", \"nope\"]",
            "`splits.ood.test[2]` names no task: \"nope\"",
        ),
        (
            "train = [\"g0\", \"g1\", \"g2\"]",
            "train = [\"g0\", \"g0\", \"g2\"]",
            "`splits.main.train[1]` names \"g0\" a second time",
        ),
        ("train = [\"g0\", \"g1\", \"g2\"]", "train = []", "`splits.main.train` is empty"),
        (
            "name = \"g1\"",
            "name = \"g0\"",
            "`tasks[1].name` is \"g0\", already the name of tasks[0]",
        ),
        (
            "expert_return = 9.0",
            "expert_return = 0.5",
            "`tasks[3].expert_return` is 0.5, not above random_return",
        ),
        ("params = { goal = 0.25 }", "params = { goal = nan }", "`tasks[1].params.goal` is NaN"),
        (
            "params = { goal = 0.25 }",
            "params = 1.0",
            "`tasks[1].params` is a float; it must be a table",
        ),
        ("obs_dim = 2", "obs_dim = 0", "`obs_dim` is 0; it must be between 1"),
        ("act_dim = 1", "act_dim = -2", "`act_dim` is -2"),
        ("rtg_scale = 10", "rtg_scale = inf", "`rtg_scale` is inf; it must be a finite number"),
        ("rtg_scale = 10", "rtg_scale = 0", "`rtg_scale` is 0; it must be above 0"),
        (
            "prompt_length = 3",
            "prompt_length = 500",
            "`prompt_length` is 500, longer than an episode",
        ),
        (
            "name = \"toy_line\"",
            "name = \"point_robot\"",
            "`name` is \"point_robot\", a built-in family's name",
        ),
        (
            "name = \"toy_line\"",
            "name = \"my suite/1\"",
            "`name` is \"my suite/1\"; it names the data files",
        ),
        (
            "task_keyword = \"task\"",
            "task_keyword = \"task\"\nstep_timeout_s = -1.0",
            "`environment.step_timeout_s` is -1",
        ),
    ];
    for (from, to, want) in cases {
        let msg = error(&edit(from, to));
        assert!(msg.contains(want), "{to}: want {want:?} in\n{msg}");
    }
}

#[test]
fn no_split_and_no_task_are_refused() {
    let good = good();
    let head = good.split("[[tasks]]").next().unwrap();
    let msg = error(&format!("{head}\ntasks = []\n[splits]\n"));
    assert!(msg.contains("`tasks` is empty"), "{msg}");
    let no_splits = good.split("[splits.main]").next().unwrap().to_owned() + "[splits]\n";
    let msg = error(&no_splits);
    assert!(msg.contains("`splits` declares no split"), "{msg}");
}

#[test]
fn a_missing_or_unreadable_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nope.toml");
    let e = family(path.to_str().unwrap()).err().unwrap();
    assert!(matches!(e, EnvError::Suite(SuiteError::Read { .. })), "{e:?}");
    assert!(e.to_string().contains("nope.toml"), "{e}");
    let msg = error("name = [");
    assert!(msg.contains("suite file"), "{msg}");
    // A name not ending in .toml is still a family name, and the error says suites exist.
    let e = family("my_tasks").err().unwrap().to_string();
    assert!(e.contains("suite file ending in .toml"), "{e}");
}

#[test]
fn splits_keep_the_file_order_and_the_first_is_the_default() {
    // Not alphabetical: a sorted map would make `ood` the first.
    let text = good().replace("[splits.main]", "[splits.zz_main]");
    let dir = tempfile::tempdir().unwrap();
    let f = SuiteFamily::load(&write(dir.path(), &text)).unwrap();
    assert_eq!(f.split_names(), vec!["zz_main", "ood"]);
    assert_eq!(f.split("default").unwrap(), (vec![0, 1, 2], vec![3, 4]));
    let text = text
        .replace("[splits.zz_main]", "[splits.ood_first]")
        .replace("[splits.ood]", "[splits.aa]");
    let path = write(dir.path(), &text);
    let f = SuiteFamily::load(&path).unwrap();
    assert_eq!(f.split_names(), vec!["ood_first", "aa"]);
    assert_eq!(f.split("default").unwrap(), (vec![0, 1, 2], vec![3, 4]));
}
