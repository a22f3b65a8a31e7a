"""make_vec equals the Rust environments stepped one by one; gymnasium's API."""
import numpy as np
import pytest

import promptdt
from promptdt import _native
from promptdt.envs import make_vec

gym = pytest.importorskip("gymnasium")


@pytest.mark.parametrize("family,tasks", [("cheetah_vel", [0, 3, 7]), ("ant_dir", [1, 2]), ("point_robot", [0, 39])])
def test_vector_env_equals_single_envs_step_for_step(family, tasks):
    env = make_vec(family, tasks=tasks, threads=2)
    obs, info = env.reset(seed=[5, 6, 7][: len(tasks)])
    singles = [_native.VecEnv(family, [t], 0) for t in tasks]
    first = np.concatenate([s.reset([seed]) for s, seed in zip(singles, [5, 6, 7])])
    np.testing.assert_array_equal(obs, first)
    rng = np.random.default_rng(0)
    for t in range(30):
        a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        o, r, term, trunc, _ = env.step(a)
        for i, s in enumerate(singles):
            so, sr, st, su = s.step(a[i : i + 1])
            np.testing.assert_array_equal(o[i], so[0])
            assert r[i] == np.float64(sr[0]) and term[i] == st[0] and trunc[i] == su[0]
        if (term | trunc).any():
            break


def test_gymnasium_api_and_autoreset():
    env = make_vec("point_robot", 2, task=3)
    assert isinstance(env, gym.vector.VectorEnv)
    assert env.observation_space.shape == (2, 2) and env.action_space.shape == (2, 2)
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.float32 and list(info["seed"]) == [0, 1]
    again, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs, again)
    ends = 0
    for t in range(env.horizon + 1):
        obs, rew, term, trunc, _ = env.step(env.action_space.sample())
        ends += int((term | trunc).sum())
        if t == env.horizon - 1:
            assert trunc.all()
    assert ends == 2
    # The step after the end reset both (reward 0, the start state).
    assert np.all(rew == 0.0)


def test_make_vec_tasks_and_errors():
    env = make_vec("cheetah_vel", 4, tasks=[2, 7])
    assert env.tasks == [2, 2, 7, 7]
    with pytest.raises(ValueError, match="unknown environment `nope`"):
        make_vec("nope", tasks=[0])
    with pytest.raises(ValueError, match="unknown task 99 of cheetah_vel"):
        make_vec("cheetah_vel", tasks=[99])
    env.reset(seed=1)
    with pytest.raises(ValueError, match=r"actions: shape"):
        env.step(np.zeros((4, 5)))
    bad = np.zeros((4, 6))
    bad[2, 3] = np.nan
    with pytest.raises(ValueError, match=r"actions\[2, 3\] = NaN is not a finite number \(environment 2, task 7\)"):
        env.step(bad)
    # Nothing stepped: the next good step is every environment's first.
    obs, *_ = env.step(np.zeros((4, 6)))
    fresh = make_vec("cheetah_vel", 4, tasks=[2, 7])
    fresh.reset(seed=1)
    first, *_ = fresh.step(np.zeros((4, 6)))
    np.testing.assert_array_equal(obs, first)
    fams = promptdt.families()
    assert fams["cheetah_vel"]["num_tasks"] == 40 and fams["ant_dir"]["obs_dim"] == 27
    assert promptdt.task_params("cheetah_vel", 3) == {"velocity": 0.3}
    assert set(promptdt.task_params("point_robot", 3)) == {"angle", "goal"}


def test_make_vec_metaworld_reach_reports_success():
    env = make_vec("metaworld_reach", 2, tasks=[1, 6])
    obs, _ = env.reset(seed=0)
    # ML1 observations: 39 values, the goal slot zeroed.
    assert obs.shape == (2, 39) and np.all(obs[:, 36:39] == 0)
    obs, rew, term, trunc, infos = env.step(np.zeros((2, 4)))
    assert infos["success"].dtype == np.bool_ and infos["success"].shape == (2,)
    assert not infos["success"].any() and infos["_success"].all()
    assert (rew > 0).all() and not term.any() and not trunc.any()
    # Families without a success criterion put none in infos.
    c = make_vec("cheetah_vel", 1, tasks=[2])
    c.reset(seed=0)
    *_, info = c.step(np.zeros((1, 6)))
    assert "success" not in info


def test_collect_metaworld_reach_from_python(tmp_path):
    out = tmp_path / "reach"
    n = promptdt.collect("metaworld_reach", out, episodes=2, prompt_episodes=1, action_noise=0.0)
    assert n == 20 * 3 * 2  # the paper's 20 tasks x expert/medium/random x (D_i, P_i)
    ds = promptdt.load_dataset(out / "metaworld_reach-6-expert.safetensors")
    assert (ds.obs_dim, ds.act_dim, ds.env, ds.task) == (39, 4, "metaworld_reach", 6)
    a, b = ds.trajectories
    # No noise: the deterministic expert repeats itself, and it reaches the goal (reward 10).
    np.testing.assert_array_equal(a.actions, b.actions)
    assert a.rewards.max() == 10.0 and a.observations.shape == (500, 39)
    with pytest.raises(ValueError, match="action_noise is for metaworld_reach"):
        promptdt.collect("point_robot", tmp_path / "p", episodes=1, action_noise=0.1)


def test_dial_from_python(tmp_path):
    fams = promptdt.families()
    d = fams["dial"]
    assert (d["num_tasks"], d["obs_dim"], d["act_dim"], d["horizon"], d["prompt_length"]) == (10, 39, 9, 200, 15)
    assert d["splits"]["default"] == ([1, 2, 3, 4, 5, 8], [6, 7, 9, 0])
    env = make_vec("dial", 2, tasks=[6, 0])
    obs, _ = env.reset(seed=0)
    assert obs.shape == (2, 39)
    obs, rew, term, trunc, infos = env.step(np.zeros((2, 9)))
    assert infos["success"].dtype == np.bool_ and not infos["success"].any() and infos["_success"].all()
    assert (rew == 0).all() and not term.any() and not trunc.any()
    with pytest.raises(ValueError, match="9"):
        env.step(np.zeros((2, 6)))
    n = promptdt.collect("dial", tmp_path / "dial", episodes=2, prompt_episodes=1)
    assert n == 10 * 3 * 2  # 10 digits x expert/medium/random x (D_i, P_i)
    ds = promptdt.load_dataset(tmp_path / "dial" / "dial-7-expert.safetensors")
    assert (ds.obs_dim, ds.act_dim, ds.env, ds.task) == (39, 9, "dial", 7)
    for t in ds.trajectories:
        # Sparse reward: 1 on the last step, where the episode terminates.
        assert t.rewards[-1] == 1.0 and t.rewards[:-1].sum() == 0.0
    with pytest.raises(ValueError, match="action_noise is for metaworld_reach"):
        promptdt.collect("dial", tmp_path / "d2", episodes=1, action_noise=0.1)


def test_family_knowledge_comes_from_rust(tmp_path):
    """Every family's action box, success rule and collection route are pdt-envs' answers: the
    package names no family (crates/cli/tests/it/families.rs checks its sources)."""
    fams = promptdt.families()
    assert set(fams) == {"point_robot", "cheetah_dir", "cheetah_vel", "ant_dir", "metaworld_reach", "dial"}
    for name, f in fams.items():
        env = make_vec(name, 1, task=0)
        space = env.single_action_space
        np.testing.assert_array_equal(space.low, np.asarray(f["action_low"], np.float32), err_msg=name)
        np.testing.assert_array_equal(space.high, np.asarray(f["action_high"], np.float32), err_msg=name)
        assert len(f["action_low"]) == f["act_dim"] and _native.is_scripted(name) == f["scripted"]
        if not f["scripted"]:
            # Collected from an RL agent: the agent directory is read (here an empty one).
            with pytest.raises(Exception, match="agent.json"):
                promptdt.collect(name, tmp_path / name, pretrained_dir=tmp_path, episodes=1)
    assert fams["point_robot"]["action_high"] == [pytest.approx(0.1)] * 2
    assert fams["dial"]["action_high"][1] == pytest.approx(0.6) and fams["dial"]["action_low"][1] == -1.0
    assert fams["metaworld_reach"]["success_reward"] == 10.0 and fams["cheetah_vel"]["success_reward"] is None
    assert _native.is_scripted("point-robot")
    with pytest.raises(ValueError, match="unknown environment"):
        _native.is_scripted("walker")
