"""promptdt -> Minari -> promptdt is bit-equal, and minari.load_dataset opens the export."""
import numpy as np
import pytest

import promptdt

minari = pytest.importorskip("minari")


def test_round_trip_is_bit_equal(point_data, tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    exported = promptdt.export_minari(point_data, "promptdt/point_robot/expert-v0", mode="expert", tasks=[0, 3, 34])
    # Minari itself opens it, with the task metadata.
    ds = minari.load_dataset("promptdt/point_robot/expert-v0")
    assert ds.total_episodes == 60 and exported.total_episodes == 60
    meta = list(ds.storage.get_episode_metadata([0, 59]))
    assert meta[0]["options"]["task"] == 0 and meta[1]["options"]["task"] == 34
    assert meta[1]["options"]["split"] == "test" and meta[0]["options"]["split"] == "train"
    assert set(meta[0]["options"]["task_params"]) == {"angle", "goal"}
    assert ds.storage.metadata["promptdt_env"] == "point_robot"
    ep = next(ds.iterate_episodes())
    assert len(ep.observations) == len(ep.rewards) + 1
    # Back to native files, equal bit for bit to the originals.
    written = promptdt.import_minari("promptdt/point_robot/expert-v0", tmp_path / "back")
    assert [p.name for p in written] == [f"point_robot-{t}-expert.safetensors" for t in (0, 3, 34)]
    for t, path in zip((0, 3, 34), written):
        a = promptdt.load_dataset(point_data / f"point_robot-{t}-expert.safetensors")
        b = promptdt.load_dataset(path)
        assert (b.env, b.task, b.mode) == ("point_robot", t, "expert")
        assert len(a) == len(b)
        for x, y in zip(a.trajectories, b.trajectories):
            for f in ("observations", "actions", "rewards", "terminated", "truncated"):
                u, v = getattr(x, f), getattr(y, f)
                assert u.dtype == v.dtype and u.shape == v.shape
                assert u.tobytes() == v.tobytes(), f


def test_export_errors(point_data, tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    with pytest.raises(ValueError, match="no expert file for tasks \\[99\\]"):
        promptdt.export_minari(point_data, "x/y-v0", tasks=[99])
    with pytest.raises(ValueError, match="unknown split `nope`"):
        promptdt.export_minari(point_data, "x/y-v0", split="nope")
    with pytest.raises(FileNotFoundError):
        promptdt.export_minari(tmp_path / "absent", "x/y-v0")


def test_write_dataset_refuses_bad_arrays(tmp_path):
    t = dict(observations=np.zeros((3, 2)), actions=np.zeros((3, 2)), rewards=np.zeros(3),
             terminated=np.zeros(3, bool), truncated=np.array([False, True, False]))
    with pytest.raises(ValueError, match="only at|last step"):
        promptdt._native.write_dataset(str(tmp_path / "a.safetensors"), [t], 2, 2)
    t["truncated"] = np.array([False, False, True])
    t["rewards"] = np.array([0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="finite|NaN"):
        promptdt._native.write_dataset(str(tmp_path / "a.safetensors"), [t], 2, 2)
    t["rewards"] = np.zeros(3)
    t["actions"] = np.zeros((3, 5))
    with pytest.raises(ValueError, match=r"`actions` has shape \[3, 5\], expected \[T, 2\]"):
        promptdt._native.write_dataset(str(tmp_path / "a.safetensors"), [t], 2, 2)
    assert not (tmp_path / "a.safetensors").exists()
