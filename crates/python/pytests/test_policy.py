"""A Policy acting through make_vec takes `promptdt eval`'s actions and returns."""
import json

import numpy as np
import pytest

import promptdt
from promptdt.envs import make_vec


def rollout(policy, plan, family, threads=2):
    """All episodes of all tasks together, as `promptdt eval` runs them: returns per episode."""
    tasks = [t.index for t in plan for _ in t.seeds]
    seeds = [s for t in plan for s in t.seeds]
    env = make_vec(family, tasks=tasks, threads=threads)
    obs, _ = env.reset(seed=seeds)
    policy.reset(len(tasks))
    policy.set_prompt([t.prompt for t in plan for _ in t.seeds])
    actions = policy.act(obs)
    returns = np.zeros(len(tasks))
    running = np.ones(len(tasks), dtype=bool)
    for _ in range(env.horizon):
        obs, rew, term, trunc, _ = env.step(actions)
        returns += np.where(running, rew, 0.0)
        running &= ~(term | trunc)
        if not running.any():
            break
        actions = policy.act(obs, rew)
    return returns


def test_policy_rollout_equals_promptdt_eval(point_run):
    result = promptdt.evaluate(point_run, episodes=3)
    promptdt.set_num_threads(1)
    policy = promptdt.Policy.load(point_run, threads=1)
    assert policy.method == "prompt-dt" and policy.env == "point_robot"
    plan = policy.eval_plan("test", episodes=3)
    assert [t.name for t in plan] == [t["task"] for t in result["tasks"]]
    returns = rollout(policy, plan, "point_robot")
    expected = np.array([r for t in result["tasks"] for r in t["returns"]])
    # Bit for bit: the same prompts, seeds, batch and kernels as the evaluator.
    assert returns.tolist() == expected.tolist()
    # And the file it wrote says the same.
    written = json.loads((point_run / "eval_final.json").read_text())
    assert written["mean_return"] == result["mean_return"]


def test_act_keeps_each_episode_history(point_run):
    policy = promptdt.Policy.load(point_run, threads=1)
    prompt = policy.task_prompt(policy.prompt_tasks()[0], seed=3)
    assert prompt.steps == policy.prompt_steps
    assert prompt.states.shape == (prompt.steps, policy.obs_dim)
    # One episode alone (one policy), and the same episode batched with another (a second one):
    # the same actions, within a few f32 ulps (batch size picks other kernels).
    other = promptdt.Policy.load(point_run, threads=1)
    env = make_vec("point_robot", tasks=[0, 5])
    obs, _ = env.reset(seed=[11, 12])
    policy.set_prompt(prompt)
    other.set_prompt([prompt, policy.task_prompt(policy.prompt_tasks()[1])])
    policy.reset(1)
    other.reset(2)
    alone, both = [policy.act(obs[:1])], [other.act(obs)]
    for _ in range(5):
        o, r, *_ = env.step(np.concatenate([alone[-1], both[-1][1:]]))
        alone.append(policy.act(o[:1], r[:1]))
        both.append(other.act(o, r))
    for a, b in zip(alone, both):
        np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-6)
    assert policy.episode_returns()[0] is not None


def test_prompt_from_arrays_equals_drawn_prompt(point_run, point_data):
    policy = promptdt.Policy.load(point_run, threads=1)
    ds = promptdt.load_dataset(point_data / "point_robot-0-prompt-expert.safetensors")
    t = ds.trajectories[0]
    n = policy.prompt_steps
    rtg = np.cumsum(t.rewards[::-1].astype(np.float64))[::-1]
    p = policy.prompt(t.observations[:n], t.actions[:n], rtg[:n], np.arange(n))
    assert p.steps == n
    assert np.all(p.mask == 1)


def test_bad_input_raises_clear_errors(point_run, tmp_path):
    policy = promptdt.Policy.load(point_run, threads=1)
    with pytest.raises(ValueError, match="call reset"):
        policy.act(np.zeros((1, policy.obs_dim)))
    policy.reset(2)
    with pytest.raises(ValueError, match="set_prompt"):
        policy.act(np.zeros((2, policy.obs_dim)))
    policy.set_prompt(policy.task_prompt(policy.prompt_tasks()[0]))
    with pytest.raises(ValueError, match=r"obs: shape \[2, 3\], expected \[2, 2\]"):
        policy.act(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="episode 1: observation\\[0\\] = NaN|not a finite"):
        policy.act(np.array([[0.0, 0.0], [np.nan, 0.0]]))
    policy.act(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="pass the rewards"):
        policy.act(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="reward: 3 values for 2 episodes"):
        policy.act(np.zeros((2, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="prompt: states, actions, returns_to_go and timesteps"):
        policy.prompt(np.zeros((3, 2)), np.zeros((2, 2)), np.zeros(3), np.arange(3))
    with pytest.raises(ValueError, match="prompt.timesteps"):
        policy.prompt(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), np.array([0, 1, 10**6]))
    with pytest.raises(ValueError, match="not one of the run's tasks"):
        policy.task_prompt(99)
    with pytest.raises(FileNotFoundError, match="no-such-run"):
        promptdt.Policy.load(tmp_path / "no-such-run")
    with pytest.raises(ValueError, match="not a run directory"):
        promptdt.Policy.load(tmp_path)
    with pytest.raises(ValueError, match="device"):
        promptdt.Policy.load(point_run, device="tpu")


def test_policy_refuses_what_serve_refuses(point_run):
    """The checks `promptdt serve` makes (one runtime, pdt-policy): target return, rewards,
    returns-to-go beyond range, prompt returns-to-go, actions that come out not finite; a refused
    call changes nothing."""
    policy = promptdt.Policy.load(point_run, threads=1)
    policy.set_prompt(policy.task_prompt(policy.prompt_tasks()[0]))
    with pytest.raises(ValueError, match="target_return 1e31 is outside the accepted range"):
        policy.reset(1, target_return=1e31)
    with pytest.raises(ValueError, match="target_return NaN is not a finite number"):
        policy.reset(1, target_return=float("nan"))
    obs = np.zeros((1, policy.obs_dim))
    # Within range, but far enough from the data to overflow inside the model: refused by name,
    # and the episode is not started.
    policy.reset(1, target_return=1e30)
    with pytest.raises(ValueError, match=r"episode 0: the policy's action is not finite .* "
                       r"target_return = 1e30 .* The call is refused"):
        policy.act(obs)
    assert policy.episode_returns() == [None]
    policy.reset(1)
    first = policy.act(obs)
    assert first.shape == (1, policy.act_dim) and np.isfinite(first).all()
    with pytest.raises(ValueError, match="episode 0: reward -1e31 is outside the accepted range"):
        policy.act(obs, np.array([-1e31]))
    with pytest.raises(ValueError, match="episode 0: reward inf is not a finite number"):
        policy.act(obs, np.array([np.inf]))
    # A reward in range whose return-to-go (target minus rewards so far) is not, or overflows the
    # model: refused either way (pdt-policy's tests check each check on its own).
    with pytest.raises(ValueError, match="would take the episode's return-to-go|is not finite"):
        policy.act(obs, np.array([-1e30]))
    assert policy.episode_returns() == [0.0]
    # The episode goes on as it was: its second step.
    policy.act(obs, np.array([0.5]))
    assert policy.episode_returns() == [0.5]
    with pytest.raises(ValueError, match=r"prompt.returns_to_go\[0\] = 1e31 is outside"):
        policy.prompt(np.zeros((1, 2)), np.zeros((1, 2)), np.array([1e31]), np.array([0]))


def test_act_with_done_follows_episode_boundaries(point_run):
    """Issue 34 point 2: a loop of 3 x horizon steps that passes the env's done flags to `act`
    (NEXT_STEP autoreset: the step after an end is the new episode's first) gives each episode
    the return it has when the episodes are run one by one, restarting the policy's episode one
    step after its end."""
    n, task = 3, 0

    def prompted():
        p = promptdt.Policy.load(point_run, threads=1)
        p.set_prompt(p.task_prompt(p.prompt_tasks()[0]))
        p.reset(n)
        return p

    def segments(rewards, ends):
        """Per environment, the return of each episode (rewards up to and including its end)."""
        out = [[] for _ in range(n)]
        acc = np.zeros(n)
        for r, e in zip(rewards, ends):
            acc += r
            for i in np.flatnonzero(e):
                out[i].append(acc[i])
                acc[i] = 0.0
        return out

    # With `done`: the policy follows the boundaries itself.
    policy = prompted()
    env = make_vec("point_robot", n, task=task)
    obs, _ = env.reset(seed=0)
    actions = policy.act(obs)
    rewards, ends, finals = [], [], [[] for _ in range(n)]
    for _ in range(3 * env.horizon):
        obs, rew, term, trunc, _ = env.step(actions)
        done = term | trunc
        actions = policy.act(obs, rew, done=done)
        rewards.append(rew)
        ends.append(done)
        if done.any():
            assert np.all(actions[done] == 0)  # ignored by the autoreset
            for i in np.flatnonzero(done):
                finals[i].append(policy.episode_returns()[i])
    with_done = segments(rewards, ends)

    # One by one: the episode restarted the step after its end, as docs/python.md said before.
    ref = prompted()
    env = make_vec("point_robot", n, task=task)
    obs, _ = env.reset(seed=0)
    actions = ref.act(obs)
    rewards, ends, prev = [], [], np.zeros(n, bool)
    for _ in range(3 * env.horizon):
        obs, rew, term, trunc, _ = env.step(actions)
        if prev.any():
            ref.restart(np.flatnonzero(prev).tolist())
            fresh = ref.act(obs, rew)
        elif (term | trunc).any():
            fresh = np.zeros_like(actions)  # the autoreset ignores it
        else:
            fresh = ref.act(obs, rew)
        actions, prev = fresh, term | trunc
        rewards.append(rew)
        ends.append(term | trunc)
    one_by_one = segments(rewards, ends)

    assert all(len(s) >= 2 for s in with_done), with_done
    assert with_done == one_by_one
    # `episode_returns` holds the ended episode's return until its next observation.
    for i in range(n):
        np.testing.assert_allclose(finals[i], with_done[i], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="done: 2 values for 3 episodes"):
        policy.act(obs, rew, done=np.zeros(2, bool))
