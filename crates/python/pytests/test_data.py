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
