"""render_mode="rgb_array": frames through MuJoCo's offscreen renderer
(headless EGL), and the point robot's drawn top view. docs/rendering.md."""
import numpy as np
import pytest

from promptdt import _native
from promptdt.envs import make_vec

pytest.importorskip("gymnasium")

MUJOCO = ["cheetah_dir", "cheetah_vel", "ant_dir", "metaworld_reach", "dial"]


@pytest.mark.parametrize("family", MUJOCO + ["point_robot"])
def test_frames_have_the_shape_change_between_steps_and_leave_the_episode_alone(family):
    env = make_vec(family, tasks=[0, 1], render_mode="rgb_array", render_size=(64, 48), threads=2)
    twin = make_vec(family, tasks=[0, 1], threads=2)
    assert env.metadata["render_modes"] == ["rgb_array"] and env.render_mode == "rgb_array"
    env.reset(seed=3)
    twin.reset(seed=3)
    frames = env.render()
    assert isinstance(frames, tuple) and len(frames) == 2
    for f in frames:
        assert f.shape == (48, 64, 3) and f.dtype == np.uint8
        # Not one colour: the scene (or the arena's grid and discs) is drawn.
        assert len(np.unique(f.reshape(-1, 3), axis=0)) > 3
    rng = np.random.default_rng(0)
    changed = 0
    prev = frames[0]
    for _ in range(5):
        a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        obs, rew, *_ = env.step(a)
        obs_t, rew_t, *_ = twin.step(a)
        # Rendering reads the state only.
        np.testing.assert_array_equal(obs, obs_t)
        np.testing.assert_array_equal(rew, rew_t)
        now = env.render()[0]
        changed += int(not np.array_equal(now, prev))
        prev = now
    assert changed >= 3, f"{family}: only {changed} of 5 frames changed"


def test_no_render_mode_renders_nothing_and_bad_arguments_are_refused():
    env = make_vec("cheetah_vel", task=0)
    assert env.render_mode is None and env.render() is None
    with pytest.raises(ValueError, match=r"render_mode: 'human'"):
        make_vec("cheetah_vel", task=0, render_mode="human")
    with pytest.raises(ValueError, match=r"render_size: \(0, 10\)"):
        make_vec("cheetah_vel", task=0, render_mode="rgb_array", render_size=(0, 10))
    with pytest.raises(ValueError, match=r"render_size: 7"):
        make_vec("cheetah_vel", task=0, render_mode="rgb_array", render_size=7)
    native = _native.VecEnv("cheetah_vel", [0], 0)
    with pytest.raises(ValueError, match=r"frame size 700x10"):
        _native.render(native, 0, 700, 10)
    with pytest.raises(ValueError, match=r"index: 1, expected 0..1"):
        _native.render(native, 1, 32, 32)
    default = _native.render(native, 0)
    assert default.shape == (480, 480, 3)


def test_the_single_env_and_gymnasium_make_render():
    import gymnasium

    import promptdt  # noqa: F401  (registers the ids)

    env = gymnasium.make(
        "promptdt/CheetahVel-v0", task=2, render_mode="rgb_array", render_size=(64, 48)
    )
    env.reset(seed=1)
    first = env.render()
    assert first.shape == (48, 64, 3) and first.dtype == np.uint8
    for _ in range(3):
        env.step(env.action_space.sample())
    assert not np.array_equal(env.render(), first)
    venv = gymnasium.make_vec("promptdt/AntDir-v0", num_envs=2, render_mode="rgb_array", render_size=(32, 32))
    venv.reset(seed=0)
    assert [f.shape for f in venv.render()] == [(32, 32, 3), (32, 32, 3)]
    plain = gymnasium.make("promptdt/CheetahVel-v0", task=2)
    plain.reset(seed=1)
    assert plain.render() is None
