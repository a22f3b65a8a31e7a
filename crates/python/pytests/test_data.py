"""load_dataset reads native files and the reference pickles as the Rust reader does."""
import json
import subprocess
import sys

import numpy as np
import pytest

import promptdt


def test_native_file_equals_safetensors_view(point_data):
    path = point_data / "point_robot-3-expert.safetensors"
    ds = promptdt.load_dataset(path)
    assert (ds.env, ds.task, ds.mode) == ("point_robot", 3, "expert")
    assert ds.obs_dim == 2 and ds.act_dim == 2 and len(ds) == 20
    # The file read independently, with the format's own layout (all steps concatenated).
    from safetensors.numpy import load_file

    raw = load_file(str(path))
    starts = raw["episode_starts"]
    assert len(starts) == len(ds) + 1
    for i, t in enumerate(ds.trajectories):
        a, b = starts[i], starts[i + 1]
        np.testing.assert_array_equal(t.observations, raw["observations"][a:b])
        np.testing.assert_array_equal(t.actions, raw["actions"][a:b])
        np.testing.assert_array_equal(t.rewards, raw["rewards"][a:b])
        np.testing.assert_array_equal(t.terminated, raw["terminated"][a:b].astype(bool))
        np.testing.assert_array_equal(t.truncated, raw["truncated"][a:b].astype(bool))
        assert t.observations.dtype == np.float32 and t.terminated.dtype == bool


def test_reference_pickle(repo):
    path = repo.parent / "shared/data/official-prompts/cheetah_vel-2-prompt-expert.pkl"
    if not path.exists():
        pytest.skip("../shared/data is not beside the checkout")
    ds = promptdt.load_dataset(path)
    assert ds.obs_dim == 20 and ds.act_dim == 6 and ds.env is None
    t = ds.trajectories[0]
    assert t.observations.shape == (len(t), 20) and t.truncated[-1] and not t.terminated.any()


def test_bad_files_raise(tmp_path):
    bad = tmp_path / "x-0-expert.safetensors"
    bad.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json")
    with pytest.raises(ValueError, match="x-0-expert.safetensors"):
        promptdt.load_dataset(bad)
    evil = tmp_path / "evil.pkl"
    evil.write_bytes(b"cos\nsystem\n(S'echo pwned'\ntR.")
    with pytest.raises(ValueError, match="evil.pkl"):
        promptdt.load_dataset(evil)
    with pytest.raises(FileNotFoundError, match="missing.pkl"):
        promptdt.load_dataset(tmp_path / "missing.pkl")
    with pytest.raises(ValueError, match="unknown file type"):
        (tmp_path / "a.txt").write_text("hi")
        promptdt.load_dataset(tmp_path / "a.txt")


def _one_trajectory(obs_dim, act_dim, steps=4):
    z = np.zeros
    return promptdt.Trajectory(observations=z((steps, obs_dim), np.float32), actions=z((steps, act_dim), np.float32),
                               rewards=z(steps, np.float32), terminated=z(steps, bool),
                               truncated=np.array([False] * (steps - 1) + [True]))


def test_write_dataset_checks_the_family(tmp_path):
    bad = promptdt.Dataset(obs_dim=3, act_dim=1, trajectories=[_one_trajectory(3, 1)], env="cheetah_vel",
                           task=0, mode="expert")
    with pytest.raises(ValueError, match=r"obs_dim 3 and act_dim 1 cannot be cheetah_vel's: "
                                         r"cheetah_vel has obs_dim 20 and act_dim 6"):
        promptdt.write_dataset(tmp_path / "a.safetensors", bad)
    bad.env = "nonsense_family"
    with pytest.raises(ValueError, match=r"unknown environment `nonsense_family` \(known: point_robot"):
        promptdt.write_dataset(tmp_path / "a.safetensors", bad)
    assert not (tmp_path / "a.safetensors").exists()
    good = promptdt.Dataset(obs_dim=2, act_dim=2, trajectories=[_one_trajectory(2, 2)], env="point_robot",
                            task=1, mode="expert")
    promptdt.write_dataset(tmp_path / "b.safetensors", good)
    assert promptdt.load_dataset(tmp_path / "b.safetensors").env == "point_robot"


def test_write_dataset_into_a_missing_directory(tmp_path):
    ds = promptdt.Dataset(obs_dim=2, act_dim=2, trajectories=[_one_trajectory(2, 2)])
    with pytest.raises(FileNotFoundError, match="nowhere"):
        promptdt.write_dataset(tmp_path / "nowhere" / "a.safetensors", ds)


def test_flat_dataset_is_every_step_in_task_order(point_data):
    flat = promptdt.flat_dataset(point_data, mode="expert", tasks=[3, 0])
    parts = [(t, promptdt.load_dataset(point_data / f"point_robot-{t}-expert.safetensors")) for t in (0, 3)]
    trajs = [(t, x) for t, ds in parts for x in ds.trajectories]
    n = sum(len(x) for _, x in trajs)
    assert len(flat) == n and flat.observations.shape == (n, 2) and flat.actions.shape == (n, 2)
    assert flat.observations.dtype == np.float32 and flat.terminals.dtype == bool
    assert flat.task_ids.dtype == np.int64 and flat.timeouts.dtype == bool
    np.testing.assert_array_equal(flat.observations, np.concatenate([x.observations for _, x in trajs]))
    np.testing.assert_array_equal(flat.rewards, np.concatenate([x.rewards for _, x in trajs]))
    np.testing.assert_array_equal(flat.timeouts, np.concatenate([x.truncated for _, x in trajs]))
    np.testing.assert_array_equal(flat.task_ids, np.concatenate([np.full(len(x), t) for t, x in trajs]))
    assert len(flat.episode_starts) == len(trajs) and (flat.env, flat.mode) == ("point_robot", "expert")
    # The same from Dataset objects.
    again = promptdt.flat_dataset([ds for _, ds in parts])
    np.testing.assert_array_equal(again.actions, flat.actions)
    np.testing.assert_array_equal(again.task_ids, flat.task_ids)


# The toy suite the front ends' tests share (5 goals on a line, data only).
_SUITE_FILE = "examples/toy_line/suite.toml"


def test_write_dataset_for_a_task_suite(repo, tmp_path):
    """A suite file's path is a family like a built-in name: its sizes checked, its name recorded
    (the name the loader finds the files under); a bad suite file is refused naming the field."""
    text = (repo / _SUITE_FILE).read_text()
    suite = tmp_path / "suite.toml"
    suite.write_text(text)
    good = promptdt.Dataset(obs_dim=2, act_dim=1, trajectories=[_one_trajectory(2, 1)], env=str(suite),
                            task=1, mode="expert")
    promptdt.write_dataset(tmp_path / "toy_line-1-expert.safetensors", good)
    assert promptdt.load_dataset(tmp_path / "toy_line-1-expert.safetensors").env == "toy_line"
    wrong = promptdt.Dataset(obs_dim=3, act_dim=1, trajectories=[_one_trajectory(3, 1)], env=str(suite),
                             task=0, mode="expert")
    with pytest.raises(ValueError, match=r"cannot be toy_line's"):
        promptdt.write_dataset(tmp_path / "toy_line-0-expert.safetensors", wrong)
    assert 'test = ["g3", "g4"]' in text
    suite.write_text(text.replace('test = ["g3", "g4"]', 'test = ["g3", "g9"]'))
    with pytest.raises(ValueError, match=r"suite.toml.*splits.main.test\[1\].* names no task"):
        promptdt.write_dataset(tmp_path / "toy_line-0-expert.safetensors", good)
    assert not (tmp_path / "toy_line-0-expert.safetensors").exists()
