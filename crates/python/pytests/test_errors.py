"""Issue 34, point 9: bad arguments raise a ValueError or TypeError that names the argument, what
was given and what is expected (before: OverflowError "can't convert negative int to unsigned",
TypeError "dimensionality mismatch", "'float' object is not iterable", AttributeError on a closed
env, "give at least one task" for num_envs=-2)."""
import errno

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

import promptdt  # noqa: E402
from promptdt import _native  # noqa: E402
from promptdt.envs import make_vec  # noqa: E402


def started_env():
    env = make_vec("cheetah_vel", 2, task=0)
    env.reset(seed=0)
    return env


def closed(env):
    env.close()
    return env


def policy_under_way(run):
    """A policy with one episode under way (its first action taken)."""
    p = promptdt.Policy.load(run, threads=1)
    p.set_prompt(p.task_prompt(p.prompt_tasks()[0]))
    p.reset(1)
    p.act(np.zeros((1, p.obs_dim)))
    return p


# (call, exception, message): `run` is a trained point-robot run.
CASES = {
    "task=-1": (lambda run: make_vec("cheetah_vel", 2, task=-1), ValueError, r"task: -1 given, expected a task index \(>= 0\)"),
    "num_envs=-2": (lambda run: make_vec("cheetah_vel", -2, task=0), ValueError, r"num_envs: -2 given, expected a number of environments \(>= 1\)"),
    "seed=-1": (lambda run: started_env().reset(seed=-1), ValueError, r"seed: -1 given, expected a seed \(in \[0, 18446744073709551616\)\)"),
    "seed list -1": (lambda run: started_env().reset(seed=[0, -1]), ValueError, r"seed\[1\]: -1 given, expected a seed"),
    "threads=-1": (lambda run: make_vec("cheetah_vel", 1, task=0, threads=-1), ValueError, r"threads: -1 given, expected a number of threads"),
    "task_params task=-1": (lambda run: promptdt.task_params("cheetah_vel", -1), ValueError, r"task: -1 given, expected a task index of cheetah_vel \(0\.\.40\)"),
    "set_num_threads(-1)": (lambda run: promptdt.set_num_threads(-1), ValueError, r"threads: -1 given, expected a number of threads"),
    "native tasks=[-1]": (lambda run: _native.VecEnv("cheetah_vel", [3, -1]), ValueError, r"tasks\[1\]: -1 given, expected task indices of cheetah_vel"),
    "float task": (lambda run: make_vec("cheetah_vel", 1, task=1.5), TypeError, r"task: 1\.5 \(float\) given, expected a task index \(an int\)"),
    "float seed": (lambda run: started_env().reset(seed=1.5), TypeError, r"seed: 1\.5 \(float\) given, expected an int"),
    "native float task": (lambda run: _native.VecEnv("cheetah_vel", [1.5]), TypeError, r"tasks\[0\]: 1\.5 \(float\) given"),
    "gym.make task=-1": (lambda run: gym.make("promptdt/CheetahVel-v0", task=-1), ValueError, r"task: -1 given"),
    "step after close": (lambda run: closed(started_env()).step(np.zeros((2, 6))), ValueError, r"step: this environment is closed"),
    "single step after close": (lambda run: closed(gym.make("promptdt/PointRobot-v0")).unwrapped.step(np.zeros(2)), ValueError, r"step: this environment is closed"),
    "policy.reset(-1)": (lambda run: promptdt.Policy.load(run).reset(-1), ValueError, r"n_episodes: -1 given, expected a number of episodes"),
    "task_prompt(-1)": (lambda run: promptdt.Policy.load(run).task_prompt(-1), ValueError, r"task: -1 given, expected a task index"),
    "task_prompt seed=-1": (lambda run: promptdt.Policy.load(run).task_prompt(0, seed=-1), ValueError, r"seed: -1 given, expected a seed"),
    "eval_plan episodes=-1": (lambda run: promptdt.Policy.load(run).eval_plan(episodes=-1), ValueError, r"episodes: -1 given, expected a number of episodes"),
    "restart([-1])": (lambda run: policy_under_way(run).restart([-1]), ValueError, r"episodes\[0\]: -1 given, expected an episode index \(0\.\.1\)"),
    "Policy.load threads=-1": (lambda run: promptdt.Policy.load(run, threads=-1), ValueError, r"threads: -1 given"),
    "1-D obs": (lambda run: policy_under_way(run).act(np.zeros(2), np.zeros(1)), ValueError, r"obs: shape \[2\], expected \[1, 2\] \(episodes, obs_dim\)"),
    "3-D obs": (lambda run: policy_under_way(run).act(np.zeros((1, 1, 2)), np.zeros(1)), ValueError, r"obs: shape \[1, 1, 2\], expected \[1, 2\]"),
    "scalar reward": (lambda run: policy_under_way(run).act(np.zeros((1, 2)), 0.5), ValueError, r"reward: shape \[\], expected \[1\] \(one per episode\)"),
    "train seed=-1": (lambda run: promptdt.train(run, seed=-1, progress=False), ValueError, r"seed: -1 given, expected a seed"),
    "train iterations=-3": (lambda run: promptdt.train(run, iterations=-3, progress=False), ValueError, r"iterations: -3 given, expected a number of iterations"),
    "train matmul=fp16": (lambda run: promptdt.train(run.parent / "m", run.parent / "tiny.toml", matmul="fp16", progress=False), ValueError, r"matmul: unknown matmul precision `fp16` \(expected fp32, tf32 or bf16\)"),
    "train matmul=tf32 on the cpu": (lambda run: promptdt.train(run.parent / "m", run.parent / "tiny.toml", matmul="tf32", progress=False), ValueError, r"matmul = tf32 needs a CUDA device, and the device is the CPU"),
    "train resume matmul": (lambda run: promptdt.train(run, resume=True, matmul="tf32", progress=False), ValueError, r"matmul: not with resume=True"),
    "evaluate episodes=-1": (lambda run: promptdt.evaluate(run, episodes=-1), ValueError, r"episodes: -1 given, expected a number of episodes"),
    "collect episodes=-1": (lambda run: promptdt.collect("point_robot", "/nonexistent", episodes=-1, progress=False), ValueError, r"episodes: -1 given, expected a number of episodes"),
    "collect seed=1.5": (lambda run: promptdt.collect("point_robot", "/nonexistent", seed=1.5, progress=False), TypeError, r"seed: 1\.5 \(float\) given, expected a seed \(an int\)"),
    "[n, 1] reward": (lambda run: policy_under_way(run).act(np.zeros((1, 2)), np.zeros((1, 1))), ValueError, r"reward: shape \[1, 1\], expected \[1\]"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_argument_raises_a_clear_error(case, point_run):
    call, exc, message = CASES[case]
    with pytest.raises(exc, match=message) as e:
        call(point_run)
    # Every refusal is also a promptdt.Error (promptdt.errors), besides the built-in kind above.
    assert isinstance(e.value, promptdt.Error), type(e.value).__mro__


def test_closed_env_error_is_gymnasiums_too():
    env = started_env()
    env.close()
    with pytest.raises(gym.error.ClosedEnvironmentError) as e:
        env.reset(seed=0)
    assert isinstance(e.value, promptdt.InvalidInputError) and isinstance(e.value, ValueError)


def test_the_error_classes_are_the_built_in_kinds_too():
    assert issubclass(promptdt.InvalidInputError, ValueError)
    assert issubclass(promptdt.ArgumentTypeError, TypeError)
    assert issubclass(promptdt.FileError, OSError)
    assert issubclass(promptdt.NotFoundError, FileNotFoundError)
    assert issubclass(promptdt.NotFoundError, promptdt.FileError)
    assert issubclass(promptdt.StateError, RuntimeError)
    for cls in (promptdt.InvalidInputError, promptdt.ArgumentTypeError, promptdt.FileError,
                promptdt.NotFoundError, promptdt.StateError):
        assert issubclass(cls, promptdt.Error)


def test_an_os_failure_in_the_library_is_a_file_error_with_its_errno(tmp_path):
    # The library creates the output directory: under a regular file the system call fails with
    # ENOTDIR, which must reach Python as an OSError carrying that errno, not as a ValueError.
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    with pytest.raises(promptdt.FileError) as e:
        promptdt.collect("point_robot", blocker / "data", episodes=1, prompt_episodes=1, progress=False)
    assert e.value.errno == errno.ENOTDIR, (e.value.errno, str(e.value))
    assert "a-file" in str(e.value)
    assert not isinstance(e.value, ValueError) and not isinstance(e.value, promptdt.NotFoundError)


# Issue 56: messages of the library crates worded for the command line (`--resume`, `--out`,
# `--data DIR`, `--iterations`, `promptdt train ...`) or for the checkout (`scripts/...`), as a
# Python caller gets them.
def _no_cli_words(message):
    for word in ("--", "scripts/", "promptdt train"):
        assert word not in message, message


def test_train_into_a_run_says_resume_true(point_run, point_data):
    with pytest.raises(ValueError, match=r"already holds a run; continue it with "
                       r"promptdt\.train\(out, resume=True\) or pick another out") as e:
        promptdt.train(point_run, point_run.parent / "tiny.toml", data=point_data, progress=False)
    _no_cli_words(str(e.value))


def test_resume_with_fewer_iterations_names_the_keyword(point_run):
    with pytest.raises(ValueError, match=r"^iterations=1: the run in .* has already done 4") as e:
        promptdt.train(point_run, resume=True, iterations=1, progress=False)
    _no_cli_words(str(e.value))


def test_evaluate_with_other_data_says_data_keyword(point_run, tmp_path):
    other = tmp_path / "other"
    promptdt.collect("point_robot", other, seed=1, episodes=20, prompt_episodes=5, progress=False)
    with pytest.raises(ValueError, match=r"\(data=DIR where it moved\)") as e:
        promptdt.evaluate(point_run, data=other, progress=False)
    _no_cli_words(str(e.value))


def test_half_created_run_directories_say_what_to_call(point_run, tmp_path):
    # Killed after run.json, before config.toml: nothing to resume.
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "run.json").write_bytes((point_run / "run.json").read_bytes())
    with pytest.raises(ValueError, match=r"delete it or rerun promptdt\.train\(config=\.\.\., out=.*bare\)$") as e:
        promptdt.train(bare, resume=True, progress=False)
    _no_cli_words(str(e.value))
    # Killed after config.toml, before task_stats.json: resume recreates it.
    half = tmp_path / "half"
    half.mkdir()
    for name in ("run.json", "config.toml"):
        (half / name).write_bytes((point_run / name).read_bytes())
    with pytest.raises(ValueError, match=r"promptdt\.train\(out, resume=True\) recreates it") as e:
        promptdt.evaluate(half, progress=False)
    _no_cli_words(str(e.value))


def test_cuda_without_its_libraries_says_what_to_install(point_run):
    try:
        promptdt.Policy.load(point_run, device="cuda")
    except ValueError as e:
        message = str(e)
    else:
        pytest.skip("CUDA works in this process")
    assert "libtorch_cuda.so could not be loaded" in message and "pip install torch==2.11.0" in message
    assert "LD_LIBRARY_PATH" in message
    _no_cli_words(message)


@pytest.mark.parametrize("kind", ["single", "vector"])
def test_string_actions_name_the_argument(kind):
    """Issue 56: numpy's "could not convert string to float" named neither `action(s)` nor what
    was given."""
    if kind == "single":
        env = gym.make("promptdt/PointRobot-v0").unwrapped
        env.reset(seed=0)
        call, name = (lambda: env.step("left")), "action"
    else:
        env = started_env()
        call, name = (lambda: env.step([["a"] * 6, ["b"] * 6])), "actions"
    with pytest.raises(ValueError, match=rf"^{name}: .* given, expected an array of floats"):
        call()
