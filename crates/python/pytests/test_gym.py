"""Issue 34, points 3 and 11: the families as registered gymnasium environments (a single
`gymnasium.Env` and our vector env), `make_vec` in gymnasium's argument order, reset infos' `_key`
masks and `reset(options=...)`."""
import warnings

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

import promptdt  # noqa: E402  (registers the ids)
from promptdt.envs import ENV_IDS, PromptDTEnv, PromptDTVectorEnv, env_id, make_vec  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402


def test_every_family_is_registered_once():
    fams = promptdt.families()
    assert sorted(ENV_IDS.values()) == sorted(fams)
    assert env_id("cheetah_vel") == "promptdt/CheetahVel-v0" and env_id("point_robot") == "promptdt/PointRobot-v0"
    for gid in ENV_IDS:
        assert gid in gym.registry, gid


@pytest.mark.parametrize("gid", sorted(ENV_IDS))
def test_check_env_passes_for_every_family(gid):
    family = ENV_IDS[gid]
    task = promptdt.families()[family]["num_tasks"] - 1
    env = gym.make(gid, task=task)
    assert isinstance(env.unwrapped, PromptDTEnv) and isinstance(env.unwrapped, gym.Env)
    assert env.unwrapped.task == task and env.unwrapped.family == family
    with warnings.catch_warnings():
        # gymnasium only advises a [-1, 1] action box (the point robot's is [-0.1, 0.1]).
        warnings.filterwarnings("ignore", message=".*symmetric and normalized.*")
        # Nor are observations bounded (gymnasium's own MuJoCo envs use the same infinite box).
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is -?infinity.*")
        check_env(env.unwrapped)
    env.close()


def test_sb3_style_loop_on_the_single_env_equals_the_vector_env():
    env = gym.make("promptdt/CheetahVel-v0", task=3)
    assert env.observation_space.shape == (20,) and env.action_space.shape == (6,)
    venv = make_vec("cheetah_vel", 1, task=3)
    obs, info = env.reset(seed=0)
    vobs, _ = venv.reset(seed=0)
    assert info == {"task": 3, "seed": 0}
    np.testing.assert_array_equal(obs, vobs[0])
    rng = np.random.default_rng(1)
    steps, ret = 0, 0.0
    for _ in range(50):
        a = rng.uniform(-1, 1, 6).astype(np.float32)
        obs, r, term, trunc, info = env.step(a)
        vo, vr, vt, vu, _ = venv.step(a[None])
        assert isinstance(r, float) and isinstance(term, bool) and isinstance(trunc, bool)
        np.testing.assert_array_equal(obs, vo[0])
        assert r == vr[0] and term == vt[0] and trunc == vu[0]
        ret += r
        steps += 1
        if term or trunc:
            obs, info = env.reset()
    assert steps == 50 and np.isfinite(ret)
    # The horizon ends a single env's episode (itself, and gymnasium's TimeLimit at the same step).
    p = gym.make("promptdt/PointRobot-v0", task=0)
    p.reset(seed=1)
    ends = [p.step(np.zeros(2, np.float32))[3] for _ in range(p.unwrapped.horizon)]
    assert ends[-1] and not any(ends[:-1])


def test_gymnasium_make_vec_works_in_every_mode():
    v = gym.make_vec("promptdt/CheetahVel-v0", num_envs=8, task=3)
    assert isinstance(v, PromptDTVectorEnv) and v.num_envs == 8 and v.tasks == [3] * 8
    obs, info = v.reset(seed=0)
    assert obs.shape == (8, 20) and obs.dtype == np.float32
    o, r, term, trunc, _ = v.step(v.action_space.sample())
    assert o.shape == (8, 20) and r.shape == (8,)
    t = gym.make_vec("promptdt/PointRobot-v0", num_envs=2, tasks=[4, 9])
    assert t.tasks == [4, 9]
    sync = gym.make_vec("promptdt/CheetahVel-v0", num_envs=2, vectorization_mode="sync", task=3)
    so, _ = sync.reset(seed=0)
    vo, _ = make_vec("cheetah_vel", 2, task=3).reset(seed=0)
    # gymnasium's SyncVectorEnv over the single envs: the same seeds, the same environments.
    np.testing.assert_array_equal(so, vo)
    sync.step(sync.action_space.sample())
    sync.close()
    # gymnasium's AsyncVectorEnv (a process per env) too.
    asy = gym.make_vec("promptdt/CheetahVel-v0", num_envs=2, vectorization_mode="async", task=3)
    ao, _ = asy.reset(seed=0)
    np.testing.assert_array_equal(ao, vo)
    asy.close()
    # gymnasium's vector wrappers work on ours.
    w = gym.wrappers.vector.RecordEpisodeStatistics(gym.make_vec("promptdt/PointRobot-v0", num_envs=2))
    w.reset(seed=0)
    ended = 0
    for _ in range(21):
        *_, info = w.step(np.zeros((2, 2), np.float32))
        ended += int(info.get("_episode", np.zeros(2, bool)).sum())
    assert ended == 2


def test_make_vec_follows_gymnasium_argument_order():
    env = make_vec("cheetah_vel", 4, tasks=[2, 7])
    assert env.tasks == [2, 2, 7, 7]
    assert make_vec("promptdt/CheetahVel-v0", num_envs=3, task=5).tasks == [5, 5, 5]
    assert promptdt.make_vec("point_robot", 2, task=1).num_envs == 2
    # The old positional use (task second) is refused, not read as one env of task 8.
    with pytest.raises(TypeError, match="give the task by keyword.*second positional argument is num_envs"):
        make_vec("cheetah_vel", 8)
    with pytest.raises(TypeError, match="num_envs: \\[2, 7\\] .*tasks go by keyword"):
        make_vec("cheetah_vel", [2, 7])
    for bad in (0, -2):
        with pytest.raises(ValueError, match=f"num_envs: {bad} given, expected a number of environments \\(>= 1\\)"):
            make_vec("cheetah_vel", bad, task=0)
    with pytest.raises(ValueError, match="num_envs: 3 given, expected a multiple of the 2 tasks"):
        make_vec("cheetah_vel", 3, tasks=[2, 7])
    doc = make_vec.__doc__ or ""
    for family in promptdt.families():
        assert family in doc, family


def test_reset_infos_carry_key_masks():
    env = make_vec("point_robot", 3, tasks=[1, 2, 3])
    _, info = env.reset(seed=4)
    assert list(info["task"]) == [1, 2, 3] and list(info["seed"]) == [4, 5, 6]
    for key in ("task", "seed"):
        assert info[f"_{key}"].dtype == np.bool_ and info[f"_{key}"].shape == (3,) and info[f"_{key}"].all()


def test_reset_options_are_honoured_or_refused():
    env = make_vec("cheetah_vel", 2, task=0)
    obs0, _ = env.reset(seed=0)
    obs, info = env.reset(seed=0, options={"task": 5})
    assert env.tasks == [5, 5] and list(info["task"]) == [5, 5]
    ref = make_vec("cheetah_vel", 2, task=5)
    np.testing.assert_array_equal(obs, ref.reset(seed=0)[0])
    a = np.full((2, 6), 0.3, np.float32)
    np.testing.assert_array_equal(env.step(a)[1], ref.step(a)[1])
    env.reset(seed=0, options={"task": [1, 2]})
    assert env.tasks == [1, 2]
    with pytest.raises(ValueError, match=r"options: unknown key\(s\) \['goal'\]"):
        env.reset(options={"goal": 3})
    with pytest.raises(ValueError, match=r"options\['task'\]: 3 tasks given, expected one, or one per environment \(2\)"):
        env.reset(options={"task": [1, 2, 3]})
    with pytest.raises(ValueError, match="unknown task 99 of cheetah_vel"):
        env.reset(options={"task": 99})
    single = gym.make("promptdt/CheetahVel-v0", task=0)
    single.reset(seed=0, options={"task": 7})
    assert single.unwrapped.task == 7
    with pytest.raises(ValueError, match=r"options: unknown key\(s\) \['reset_mask'\]"):
        single.reset(options={"reset_mask": np.ones(1, bool)})


@pytest.mark.parametrize("gid", sorted(ENV_IDS))
def test_spec_has_the_horizon_and_metadata_a_frame_rate(gid):
    """Issue 56: the spec had no max_episode_steps and the metadata no render_fps (what SB3 and
    gymnasium's RecordVideo read)."""
    family = ENV_IDS[gid]
    horizon = promptdt.families()[family]["horizon"]
    assert gym.spec(gid).max_episode_steps == horizon
    env = gym.make(gid)
    assert env.spec.max_episode_steps == horizon
    fps = env.metadata["render_fps"]
    assert isinstance(fps, int) and fps > 0 and env.metadata["render_modes"] == ["rgb_array"]
    assert gym.make_vec(gid, num_envs=2).metadata["render_fps"] == fps
    # The simulated time a step stands for: 1 / dt of the MuJoCo families (gym's own Cheetah and
    # Ant render at 20 frames a second, Meta-World at 80).
    expected = {"cheetah_dir": 20, "cheetah_vel": 20, "ant_dir": 20, "metaworld_reach": 80, "dial": 25}
    if family in expected:
        assert fps == expected[family]
    env.close()


def test_time_limit_of_the_spec_ends_episodes_where_the_env_does():
    env = gym.make("promptdt/PointRobot-v0", task=2)
    env.reset(seed=0)
    steps = 0
    while True:
        _, _, term, trunc, _ = env.step(np.zeros(2, np.float32))
        steps += 1
        if term or trunc:
            break
    assert steps == env.spec.max_episode_steps == env.unwrapped.horizon


def test_make_vec_takes_the_spec_limit_and_refuses_another():
    v = gym.make_vec("promptdt/PointRobot-v0", num_envs=2, task=1)
    assert v.spec.max_episode_steps == v.horizon
    with pytest.raises(ValueError, match=r"max_episode_steps: 5 given; .*horizon \(20\).*vectorization_mode='sync'"):
        gym.make_vec("promptdt/PointRobot-v0", num_envs=2, task=1, max_episode_steps=5)
    sync = gym.make_vec("promptdt/PointRobot-v0", num_envs=2, vectorization_mode="sync", task=1,
                        max_episode_steps=5)
    sync.reset(seed=0)
    ends = [sync.step(np.zeros((2, 2), np.float32))[3].all() for _ in range(5)]
    assert ends == [False] * 4 + [True]
