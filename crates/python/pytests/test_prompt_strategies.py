"""Test-time prompt strategies from Python: ``Policy.task_prompt(prompt_strategy=...)``
acts as ``promptdt eval`` would with the prompt the strategy chose, and
``promptdt.evaluate(prompt_strategy=...)`` evaluates every strategy, its choices logged."""
import json

import numpy as np
import pytest

import promptdt
from promptdt.envs import make_vec

from test_policy import rollout


def test_every_strategy_evaluates_and_logs_its_choices(point_run):
    reference = promptdt.evaluate(point_run, episodes=2)
    assert "picks" not in reference
    for name in ["random-segment", "best-return", "nearest-start", "bandit"]:
        r = promptdt.evaluate(point_run, episodes=2, prompt_strategy=name, prompt_length=3)
        assert r["prompt_strategy"]["strategy"] == name
        assert r["prompt_strategy"]["length"] == 3
        assert [t["task"] for t in r["tasks"]] == [t["task"] for t in reference["tasks"]]
        assert all(len(p["segments"]) == 1 for p in r["picks"]), r["picks"]
        written = json.loads((point_run / f"eval_prompt_{name}.json").read_text())
        assert written["mean_return"] == r["mean_return"]
    # eval_final.json stays the reference rule's
    assert json.loads((point_run / "eval_final.json").read_text())["mean_return"] == reference["mean_return"]


def test_strategy_prompts_act_as_the_evaluator_with_them(point_run):
    promptdt.set_num_threads(1)
    policy = promptdt.Policy.load(point_run, threads=1)
    task = policy.prompt_tasks()[0]
    best = policy.task_prompt(task, prompt_strategy="best-return")
    assert len(best.segments) == 1 and set(best.segments[0]) == {"demo", "start"}
    assert best.steps == policy.prompt_steps
    # best-return is deterministic; random-segment depends on its seed alone
    assert policy.task_prompt(task, prompt_strategy="best-return").segments == best.segments
    r1 = policy.task_prompt(task, seed=1, prompt_strategy="random-segment", prompt_length=4)
    assert r1.steps == 4
    assert r1.segments == policy.task_prompt(task, seed=1, prompt_strategy="random-segment", prompt_length=4).segments
    draws = {str(policy.task_prompt(task, seed=s, prompt_strategy="random-segment").segments) for s in range(8)}
    assert len(draws) > 1
    # nearest-start: the prompt of the episode's own start state
    env = make_vec("point_robot", tasks=[task])
    obs, _ = env.reset(seed=[5])
    near = policy.task_prompt(task, prompt_strategy="nearest-start", observation=obs[0])
    assert len(near.segments) == 1
    # The reference rule by name is the plain draw.
    plain = policy.task_prompt(task, seed=2)
    named = policy.task_prompt(task, seed=2, prompt_strategy="reference")
    assert np.array_equal(plain.states, named.states) and named.segments == []


class _Planned:
    """A task of an evaluation plan with another prompt."""

    def __init__(self, task, prompt):
        self.index, self.seeds, self.prompt = task.index, task.seeds, prompt


def test_a_best_return_rollout_takes_the_evaluations_returns(point_run):
    # The strategy evaluation keeps the reference plan's reset seeds, so acting on the plan with
    # each task's best-return prompt gives its returns, bit for bit.
    result = promptdt.evaluate(point_run, episodes=2, prompt_strategy="best-return")
    promptdt.set_num_threads(1)
    policy = promptdt.Policy.load(point_run, threads=1)
    plan = policy.eval_plan("test", episodes=2)
    plan = [_Planned(t, policy.task_prompt(t.index, prompt_strategy="best-return")) for t in plan]
    returns = rollout(policy, plan, "point_robot")
    expected = [r for t in result["tasks"] for r in t["returns"]]
    assert returns.tolist() == expected


def test_bad_strategies_are_refused_by_name(point_run):
    policy = promptdt.Policy.load(point_run, threads=1)
    task = policy.prompt_tasks()[0]
    with pytest.raises(ValueError, match="unknown prompt strategy `tail`"):
        policy.task_prompt(task, prompt_strategy="tail")
    with pytest.raises(ValueError, match="1 x 400"):
        policy.task_prompt(task, prompt_strategy="best-return", prompt_length=400)
    with pytest.raises(ValueError, match="first observation"):
        policy.task_prompt(task, prompt_strategy="nearest-start")
    with pytest.raises(ValueError, match="bandit"):
        policy.task_prompt(task, prompt_strategy="bandit")
    with pytest.raises(ValueError, match="unknown prompt strategy `greedy`"):
        promptdt.evaluate(point_run, episodes=1, prompt_strategy="greedy")


def test_prompt_bandit_chooses_learns_and_is_seeded(point_run):
    policy = promptdt.Policy.load(point_run, threads=1)
    task = policy.prompt_tasks()[0]

    def picks(seed, paying=None):
        b = policy.prompt_bandit(task, seed=seed, epsilon=0.2)
        assert b.task == task
        out = []
        for _ in range(40):
            p = b.choose()
            assert p.steps == policy.prompt_steps and len(p.segments) == 1
            seg = p.segments[0]
            out.append((seg["demo"], seg["start"]))
            paying = paying or out[0]
            b.update(10.0 if out[-1] == paying else 0.0)
        return out

    a = picks(0)
    assert a == picks(0)
    assert a != picks(1)
    # the arm that pays is taken whenever the bandit does not explore (epsilon 0.2)
    assert sum(x == a[0] for x in a[1:]) >= 25, a
    b = policy.prompt_bandit(task, seed=0, rule="ucb", prompt_length=3)
    assert b.choose().steps == 3
    with pytest.raises(ValueError, match="unknown bandit rule `thompson`"):
        policy.prompt_bandit(task, rule="thompson")
    fresh = policy.prompt_bandit(task)
    with pytest.raises(ValueError, match="call choose"):
        fresh.update(1.0)
