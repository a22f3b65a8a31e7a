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


class OneTaskEnv:
    """Defined in gymnasium's terms below: one task of a family, for `recover_environment` where
    the package itself registers no `promptdt/...` ids."""


def _register_point_robot():
    import gymnasium as gym

    from promptdt.envs import env_id as gym_id  # the one naming, which the export uses

    env_id = gym_id("point_robot")
    assert env_id == "promptdt/PointRobot-v0"
    if env_id in gym.registry:
        return env_id

    class _Env(gym.Env):
        def __init__(self, task=0):
            self._env = promptdt._native.VecEnv("point_robot", [task], 1)
            fam = promptdt.families()["point_robot"]
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (fam["obs_dim"],), np.float32)
            self.action_space = gym.spaces.Box(np.float32(fam["action_low"][0]),
                                               np.float32(fam["action_high"][0]), (fam["act_dim"],), np.float32)
            self.task = task

        def reset(self, *, seed=None, options=None):
            return self._env.reset([seed or 0])[0], {}

        def step(self, action):
            obs, r, term, trunc = self._env.step(np.asarray([action], np.float32), [True])
            return obs[0], float(r[0]), bool(term[0]), bool(trunc[0]), {}

    globals()["OneTaskEnv"] = _Env
    gym.register(env_id, entry_point=f"{__name__}:OneTaskEnv")
    return env_id


def test_export_has_env_spec_and_no_warnings(point_data, tmp_path, monkeypatch):
    import warnings

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    env_id = _register_point_robot()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        promptdt.export_minari(point_data, "promptdt/point_robot/spec-v0", tasks=[3, 34])
        ds = minari.load_dataset("promptdt/point_robot/spec-v0")
    assert ds.spec.env_spec is not None and ds.spec.env_spec.id == env_id
    assert ds.spec.env_spec.kwargs["task"] == 3
    env = ds.recover_environment()
    assert env.spec.kwargs["task"] == 3 and env.observation_space.shape == (2,)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (2,)
    assert ds.recover_environment(task=34).spec.kwargs["task"] == 34


def test_export_picks_a_family_of_the_reference_prompt_folder(repo, tmp_path, monkeypatch):
    """The reference prompt folder holds cheetah_dir (tasks 0, 1) and cheetah_vel (0..39) files."""
    folder = repo.parent / "shared/data/official-prompts"
    if not folder.exists():
        pytest.skip("../shared/data is not beside the checkout")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))

    def tasks_of(ds):
        return sorted({m["options"]["task"] for m in ds.storage.get_episode_metadata(ds.episode_indices)})

    # Only cheetah_vel has tasks 2 and 7: it is taken.
    ds = promptdt.export_minari(folder, "ref/cheetah_vel/prompt-v0", mode="prompt-expert", tasks=[2, 7])
    assert tasks_of(ds) == [2, 7] and ds.storage.metadata["promptdt_env"] == "cheetah_vel"
    # Tasks 0 and 1 are both families': env= picks one, and without it the error names them.
    ds = promptdt.export_minari(folder, "ref/cheetah_dir/prompt-v0", mode="prompt-expert", tasks=[0, 1],
                                env="cheetah_dir")
    assert tasks_of(ds) == [0, 1] and ds.storage.metadata["promptdt_env"] == "cheetah_dir"
    assert ds.total_episodes == len(promptdt.load_dataset(folder / "cheetah_dir-0-prompt-expert.pkl")) * 2
    with pytest.raises(ValueError, match=r"several families \(cheetah_dir, cheetah_vel\).*give env="):
        promptdt.export_minari(folder, "ref/x/prompt-v0", mode="prompt-expert", tasks=[0, 1])
    with pytest.raises(ValueError, match="unknown family `nonsense`"):
        promptdt.export_minari(folder, "ref/y/prompt-v0", mode="prompt-expert", env="nonsense")


def test_minari_extra_has_what_export_imports(repo):
    """`pip install promptdt[minari]` installs what export_minari imports (PIL through Minari's
    HDF5 storage), the same packages as the install script's PROMPTDT_PY_EXTRAS=minari."""
    import importlib.metadata
    import re

    reqs = [r for r in importlib.metadata.requires("promptdt") if re.search(r"extra == .minari.", r)]
    names = {re.match(r"[A-Za-z0-9_.-]+(\[[^\]]*\])?", r).group(0).lower() for r in reqs}
    assert {"minari[hdf5]", "pillow", "gymnasium"} <= names, reqs
    script = (repo / "scripts/install_python.sh").read_text()
    line = next(x for x in script.splitlines() if "minari[hdf5]" in x)
    for pkg in ("minari[hdf5]", "pillow"):
        assert pkg in line


def _pendulum_like(tmp_path, monkeypatch):
    import gymnasium as gym

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    rng = np.random.default_rng(0)
    buf = [minari.data_collector.EpisodeBuffer(
        id=0, observations=rng.standard_normal((6, 3)).astype(np.float32),
        actions=rng.standard_normal((5, 1)).astype(np.float32), rewards=np.zeros(5),
        terminations=np.zeros(5, bool), truncations=np.array([0, 0, 0, 0, 1], bool))]
    minari.create_dataset_from_buffers(
        "other/pendulum/x-v0", buf, observation_space=gym.spaces.Box(-1, 1, (3,), np.float32),
        action_space=gym.spaces.Box(-1, 1, (1,), np.float32), algorithm_name="x", author="x",
        author_email="x", code_permalink="x", description="x")
    return "other/pendulum/x-v0"


def test_import_refuses_data_that_contradicts_its_family(tmp_path, monkeypatch):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Minari's notices about the test's own dataset
        dataset_id = _pendulum_like(tmp_path, monkeypatch)
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=r"obs_dim 3 and act_dim 1 cannot be cheetah_vel's: cheetah_vel has obs_dim 20 and act_dim 6"):
        promptdt.import_minari(dataset_id, out, env="cheetah_vel", task=0, mode="expert")
    with pytest.raises(ValueError, match=r"unknown environment `nonsense_family` \(known: .*cheetah_vel"):
        promptdt.import_minari(dataset_id, out, env="nonsense_family", task=0, mode="expert")
    assert not out.exists() or not any(out.iterdir())


# A user's own task family (a suite file) and Minari data of an environment promptdt does not know.
_SUITE = """
name = "pend_levels"
obs_dim = 3
act_dim = 1
action_bound = 2.0
max_ep_len = 50
rtg_scale = 100
target_return = -100.0
prompt_length = 5
[[tasks]]
name = "light"
params = { g = 5.0 }
[[tasks]]
name = "heavy"
params = { g = 10.0 }
[[tasks]]
name = "very_heavy"
params = { g = 15.0 }
[splits.default]
train = ["light", "heavy"]
test = ["very_heavy"]
"""


def _labelled(tmp_path, monkeypatch, dataset_id, label, dims=(3, 1)):
    """Four episodes of Pendulum's sizes, labelled by ``label(i, T)`` -> (options, infos)."""
    import gymnasium as gym

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    rng = np.random.default_rng(1)
    buffers = []
    for i in range(4):
        T = 5 + i
        options, infos = label(i, T)
        buffers.append(minari.data_collector.EpisodeBuffer(
            id=i, observations=rng.standard_normal((T + 1, dims[0])).astype(np.float32),
            actions=rng.uniform(-2, 2, (T, dims[1])).astype(np.float32),
            rewards=np.full(T, -float(i + 1)), terminations=np.zeros(T, bool),
            truncations=np.arange(T) == T - 1, options=options, infos=infos))
    minari.create_dataset_from_buffers(
        dataset_id, buffers, observation_space=gym.spaces.Box(-9, 9, (dims[0],), np.float32),
        action_space=gym.spaces.Box(-2, 2, (dims[1],), np.float32), algorithm_name="x", author="x",
        author_email="x", code_permalink="x", description="x")
    return buffers


def test_import_into_a_suite_labels_episodes_by_a_named_field(tmp_path, monkeypatch):
    import warnings

    suite = tmp_path / "levels.toml"
    suite.write_text(_SUITE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Minari's notices about the test's own datasets
        # Task names in the reset options' "level"; task indices in the infos' "task_id".
        by_name = _labelled(tmp_path, monkeypatch, "user/pend/names-v0",
                            lambda i, T: ({"level": ["light", "heavy"][i % 2]}, {}))
        by_info = _labelled(tmp_path, monkeypatch, "user/pend/infos-v0",
                            lambda i, T: ({}, {"task_id": np.full(T + 1, 2, np.int64)}))
    out = tmp_path / "data"
    written = promptdt.import_minari("user/pend/names-v0", out, env=str(suite), mode="expert",
                                     task_field="level", prompt_rule="best:1")
    assert [p.name for p in written] == [
        "pend_levels-0-expert.safetensors", "pend_levels-0-prompt-expert.safetensors",
        "pend_levels-1-expert.safetensors", "pend_levels-1-prompt-expert.safetensors"]
    light = promptdt.load_dataset(out / "pend_levels-0-expert.safetensors")
    assert (light.env, light.task, light.mode) == ("pend_levels", 0, "expert")
    assert len(light) == 2  # episodes 0 and 2
    assert light.trajectories[1].observations.tobytes() == by_name[2].observations[:-1].tobytes()
    # The prompt set: the highest-return episode (episode 0, return -5), by the library's rule.
    prompt = promptdt.load_dataset(out / "pend_levels-0-prompt-expert.safetensors")
    assert len(prompt) == 1 and prompt.trajectories[0].rewards.sum() == -5.0
    written = promptdt.import_minari("user/pend/infos-v0", out, env=str(suite), mode="medium",
                                     task_field="task_id")
    assert [p.name for p in written] == ["pend_levels-2-medium.safetensors"]
    assert len(promptdt.load_dataset(written[0])) == 4
    assert by_info[0].rewards[0] == -1.0


def test_import_into_a_suite_refuses_unlabelled_or_unknown_tasks(tmp_path, monkeypatch):
    import warnings

    suite = tmp_path / "levels.toml"
    suite.write_text(_SUITE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _labelled(tmp_path, monkeypatch, "user/pend/none-v0", lambda i, T: ({}, {}))
        _labelled(tmp_path, monkeypatch, "user/pend/bad-v0",
                  lambda i, T: ({"level": ["light", "medium_heavy"][i % 2]}, {}))
        _labelled(tmp_path, monkeypatch, "user/pend/wide-v0", lambda i, T: ({"level": "light"}, {}),
                  dims=(4, 1))
    out = tmp_path / "data"
    with pytest.raises(ValueError, match=r"episode 0: no task label: no 'task' in its options or infos"):
        promptdt.import_minari("user/pend/none-v0", out, env=str(suite), mode="expert")
    with pytest.raises(ValueError, match=r"episode 1: options\['level'\]: 'medium_heavy' is no task of .*light, heavy, very_heavy"):
        promptdt.import_minari("user/pend/bad-v0", out, env=str(suite), mode="expert", task_field="level")
    with pytest.raises(ValueError, match=r"obs_dim 4 and act_dim 1 cannot be"):
        promptdt.import_minari("user/pend/wide-v0", out, env=str(suite), mode="expert", task_field="level")
    with pytest.raises(ValueError, match=r"prompt_rule: unknown prompt rule"):
        promptdt.import_minari("user/pend/bad-v0", out, env=str(suite), mode="expert", task="light",
                               prompt_rule="top3")
    with pytest.raises(ValueError, match=r"task: 7 is no task of"):
        promptdt.import_minari("user/pend/bad-v0", out, env=str(suite), mode="expert", task=7)
    assert not out.exists() or not any(out.iterdir())
