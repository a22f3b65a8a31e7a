//! Task suites read from a file (`pdt_envs::suite`): a good suite is a family like the built-in
//! ones, found by `family(path)`; every bad field is refused, naming the file and the field.

#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use pdt_envs::suite::{SuiteError, SuiteFamily};
use pdt_envs::{family, EnvError, EnvFamily};
use std::path::{Path, PathBuf};

/// A complete suite: 4 tasks, a default split and an out-of-distribution one, per-task targets
/// and reference returns on some tasks, an environment.
const GOOD: &str = r#"
name = "pendulum_mass"
obs_dim = 3
act_dim = 1
action_bound = 2.0
max_ep_len = 200
rtg_scale = 100
target_return = -150.0
prompt_length = 5
success_reward = -0.1

[[tasks]]
name = "light"
params = { mass = 0.5, arm = [1.0, 0.1] }
expert_return = -150.0
random_return = -1200.0

[[tasks]]
name = "medium"
params = { mass = 1.0 }
target_return = -180.0

[[tasks]]
name = "heavy"
params = { mass = 2.0 }

[[tasks]]
name = "very_heavy"
params = { mass = 4.0 }

[splits.default]
train = ["light", "medium"]
test = ["heavy"]

[splits.ood]
train = ["light", "medium", "heavy"]
test = ["very_heavy"]

[environment]
entry = "gymnasium.envs.classic_control:PendulumEnv"
task_keyword = "task"
python = ".venv/bin/python"
"#;

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

/// `GOOD` with `from` replaced by `to` (which must occur).
fn edit(from: &str, to: &str) -> String {
    assert!(GOOD.contains(from), "{from}");
    GOOD.replacen(from, to, 1)
}

#[test]
fn a_suite_file_is_a_family() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(dir.path(), GOOD);
    let f = family(path.to_str().unwrap()).unwrap();
    assert_eq!(f.name(), "pendulum_mass");
    assert_eq!(f.num_tasks(), 4);
    let p = f.preset();
    assert_eq!((p.obs_dim, p.act_dim, p.horizon, p.prompt_length), (3, 1, 200, 5));
    assert_eq!((p.rtg_scale, p.target_return), (100.0, -150.0));
    assert_eq!(f.action_bounds().low, vec![-2.0]);
    assert_eq!(f.action_bounds().high, vec![2.0]);
    assert_eq!(f.success_reward(), Some(-0.1));
    assert_eq!(f.render_fps(), 30);
    // The declared order, the first split the default.
    assert_eq!(f.split_names(), vec!["default", "ood"]);
    assert_eq!(f.split("default").unwrap(), (vec![0, 1], vec![2]));
    assert_eq!(f.split("ood").unwrap(), (vec![0, 1, 2], vec![3]));
    assert!(matches!(f.split("nope"), Err(EnvError::UnknownSplit { .. })));
    assert_eq!(
        f.task_params(0).unwrap(),
        serde_json::json!({"name": "light", "params": {"mass": 0.5, "arm": [1.0, 0.1]}})
    );
    assert_eq!(f.task_target_return(1), Some(-180.0));
    assert_eq!(f.task_target_return(0), None);
    assert_eq!(f.reference_returns(0), Some((-150.0, -1200.0)));
    assert_eq!(f.reference_returns(1), None);
    // Sizes are checked against the suite like a built-in family's.
    pdt_envs::check_dims(path.to_str().unwrap(), 3, 1).unwrap();
    assert!(matches!(
        pdt_envs::check_dims(path.to_str().unwrap(), 4, 1),
        Err(EnvError::WrongDims { .. })
    ));
    // Its environment runs in the worker, never here; the interpreter's path is the file's.
    let e = f.make(0).err().unwrap().to_string();
    assert!(e.contains("Python worker"), "{e}");
    assert!(f.make(9).is_err());
    let suite = f.as_suite().unwrap();
    assert_eq!(suite.text(), GOOD);
    let env = suite.environment().unwrap();
    assert_eq!(env.python.as_deref(), Some(dir.path().join(".venv/bin/python").as_path()));
    assert_eq!(env.step_timeout_s, 60.0);
    assert_eq!(suite.worker_task(2).unwrap().params, serde_json::json!({"mass": 2.0}));
}

#[test]
fn without_an_environment_make_says_to_evaluate_offline() {
    let text = GOOD.split("[environment]").next().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let f = SuiteFamily::load(&write(dir.path(), text)).unwrap();
    assert!(f.environment().is_none());
    let e = f.make(0).err().unwrap().to_string();
    assert!(e.contains("declares no [environment]"), "{e}");
}

#[test]
fn per_dimension_bounds_and_per_task_targets() {
    let text = edit("action_bound = 2.0", "action_low = [-1.0]\naction_high = [3.0]")
        .replace("target_return = -150.0\n", "")
        .replace("name = \"light\"", "name = \"light\"\ntarget_return = -100.0")
        .replace("name = \"heavy\"", "name = \"heavy\"\ntarget_return = -300.0")
        .replace("name = \"very_heavy\"", "name = \"very_heavy\"\ntarget_return = -400.0");
    let dir = tempfile::tempdir().unwrap();
    let f = SuiteFamily::load(&write(dir.path(), &text)).unwrap();
    assert_eq!(f.action_bounds().low, vec![-1.0]);
    assert_eq!(f.action_bounds().high, vec![3.0]);
    // The largest of the tasks' targets stands for the suite (the return-token checks).
    assert_eq!(f.preset().target_return, -100.0);
    assert_eq!(f.task_target_return(3), Some(-400.0));
}

#[test]
fn a_missing_field_is_named() {
    let msg = error(&edit("obs_dim = 3\n", ""));
    assert!(msg.contains("missing field `obs_dim`"), "{msg}");
    let msg = error(&edit("name = \"heavy\"\n", ""));
    assert!(msg.contains("`tasks[2]`") && msg.contains("missing field `name`"), "{msg}");
    let msg = error(&edit("test = [\"very_heavy\"]", ""));
    assert!(msg.contains("`splits.ood`") && msg.contains("missing field `test`"), "{msg}");
    let msg = error(&edit("action_bound = 2.0", ""));
    assert!(msg.contains("`action_bound` is missing"), "{msg}");
    let msg = error(&edit("target_return = -150.0\n", ""));
    assert!(msg.contains("`target_return` is missing") && msg.contains("tasks[0]"), "{msg}");
    let msg = error(&edit("random_return = -1200.0", ""));
    assert!(msg.contains("`tasks[0].random_return` is missing"), "{msg}");
    let msg = error(&edit("entry = \"gymnasium.envs.classic_control:PendulumEnv\"", ""));
    assert!(msg.contains("`environment`") && msg.contains("missing field `entry`"), "{msg}");
}

#[test]
fn an_extra_field_is_named() {
    let msg = error(&edit("obs_dim = 3", "obs_dim = 3\nobs_size = 3"));
    assert!(msg.contains("unknown field `obs_size`"), "{msg}");
    let msg = error(&edit("params = { mass = 1.0 }", "params = { mass = 1.0 }\nweight = 2"));
    assert!(msg.contains("`tasks[1]`") && msg.contains("unknown field `weight`"), "{msg}");
    let msg = error(&edit("test = [\"heavy\"]", "test = [\"heavy\"]\nvalid = [\"heavy\"]"));
    assert!(msg.contains("`splits.default`") && msg.contains("unknown field `valid`"), "{msg}");
    let msg = error(&edit("task_keyword = \"task\"", "task_keyword = \"task\"\ntimeout = 3"));
    assert!(msg.contains("`environment`") && msg.contains("unknown field `timeout`"), "{msg}");
}

#[test]
fn a_contradictory_field_is_named() {
    let cases: &[(&str, &str, &str)] = &[
        (
            "action_bound = 2.0",
            "action_bound = 2.0\naction_low = [-1.0]\naction_high = [1.0]",
            "`action_bound` is given together",
        ),
        (
            "action_bound = 2.0",
            "action_low = [1.0]\naction_high = [1.0]",
            "`action_low[0]` is 1, not below action_high[0]",
        ),
        (
            "action_bound = 2.0",
            "action_low = [-1.0, -1.0]\naction_high = [1.0, 1.0]",
            "`action_low` has 2 values; act_dim is 1",
        ),
        (
            "test = [\"heavy\"]",
            "test = [\"heavy\", \"light\"]",
            "`splits.default.test[1]` \"light\" is also in splits.default.train",
        ),
        (
            "test = [\"very_heavy\"]",
            "test = [\"very_heavy\", \"nope\"]",
            "`splits.ood.test[1]` names no task: \"nope\"",
        ),
        (
            "train = [\"light\", \"medium\"]",
            "train = [\"light\", \"light\"]",
            "`splits.default.train[1]` names \"light\" a second time",
        ),
        ("train = [\"light\", \"medium\"]", "train = []", "`splits.default.train` is empty"),
        (
            "name = \"medium\"",
            "name = \"light\"",
            "`tasks[1].name` is \"light\", already the name of tasks[0]",
        ),
        (
            "expert_return = -150.0",
            "expert_return = -1500.0",
            "`tasks[0].expert_return` is -1500, not above random_return",
        ),
        ("params = { mass = 1.0 }", "params = { mass = nan }", "`tasks[1].params.mass` is NaN"),
        (
            "params = { mass = 1.0 }",
            "params = 1.0",
            "`tasks[1].params` is a float; it must be a table",
        ),
        ("obs_dim = 3", "obs_dim = 0", "`obs_dim` is 0; it must be between 1"),
        ("act_dim = 1", "act_dim = -2", "`act_dim` is -2"),
        ("rtg_scale = 100", "rtg_scale = inf", "`rtg_scale` is inf; it must be a finite number"),
        ("rtg_scale = 100", "rtg_scale = 0", "`rtg_scale` is 0; it must be above 0"),
        (
            "prompt_length = 5",
            "prompt_length = 500",
            "`prompt_length` is 500, longer than an episode",
        ),
        (
            "name = \"pendulum_mass\"",
            "name = \"point_robot\"",
            "`name` is \"point_robot\", a built-in family's name",
        ),
        (
            "name = \"pendulum_mass\"",
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
    let head = GOOD.split("[[tasks]]").next().unwrap();
    let msg = error(&format!("{head}\ntasks = []\n[splits]\n"));
    assert!(msg.contains("`tasks` is empty"), "{msg}");
    let no_splits = GOOD.split("[splits.default]").next().unwrap().to_owned() + "[splits]\n";
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
    let text = GOOD.replace("[splits.default]", "[splits.zz_main]");
    let dir = tempfile::tempdir().unwrap();
    let f = SuiteFamily::load(&write(dir.path(), &text)).unwrap();
    assert_eq!(f.split_names(), vec!["zz_main", "ood"]);
    assert_eq!(f.split("default").unwrap(), (vec![0, 1], vec![2]));
    let text = text
        .replace("[splits.zz_main]", "[splits.ood_first]")
        .replace("[splits.ood]", "[splits.aa]");
    let path = write(dir.path(), &text);
    let f = SuiteFamily::load(&path).unwrap();
    assert_eq!(f.split_names(), vec!["ood_first", "aa"]);
    assert_eq!(f.split("default").unwrap(), (vec![0, 1], vec![2]));
}
