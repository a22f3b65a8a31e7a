"""Evaluation-time adaptations from Python: ``promptdt.evaluate(adapt=...)``
adapts each test task before its episodes, as ``promptdt eval --adapt`` does, and
``Policy.adapt`` gives a task's adaptation to act with through ``Policy.set_prompt``."""
import json

import numpy as np
import pytest

import promptdt
from promptdt.envs import make_vec

KINDS = ["soft-prompt", "ptdt", "lora"]


def test_every_adaptation_evaluates_and_logs_what_it_did(point_run):
    reference = promptdt.evaluate(point_run, episodes=2)
    for kind in KINDS:
        r = promptdt.evaluate(point_run, episodes=2, adapt=kind, adapt_steps=2, adapt_batch=4)
        assert r["adapt"]["kind"] == kind and r["adapt"]["steps"] == 2 and r["adapt"]["batch"] == 4
        tasks = [t["task"] for t in r["tasks"]]
        assert tasks == [t["task"] for t in reference["tasks"]]
        assert [l["task"] for l in r["adapt_log"]] == tasks
        for log in r["adapt_log"]:
            assert np.isfinite(log["loss_before"]) and np.isfinite(log["loss_after"])
            assert log["trainable"] > 0
        written = json.loads((point_run / f"eval_adapt_{kind}.json").read_text())
        assert written["mean_return"] == r["mean_return"]
    # eval_final.json stays the unadapted model's
    assert json.loads((point_run / "eval_final.json").read_text())["mean_return"] == reference["mean_return"]


def _episode(policy, task, seed):
    env = make_vec("point_robot", tasks=[task], threads=1)
    obs, _ = env.reset(seed=[seed])
    policy.reset(1)
    actions, ret = [], 0.0
    a = policy.act(obs)
    for _ in range(env.horizon):
        actions.append(a.copy())
        obs, rew, term, trunc, _ = env.step(a)
        ret += float(rew[0])
        if term[0] or trunc[0]:
            break
        a = policy.act(obs, rew)
    return np.concatenate(actions), ret


def test_an_adaptation_acts_through_set_prompt_and_is_seeded(point_run):
    promptdt.set_num_threads(1)
    policy = promptdt.Policy.load(point_run, threads=1)
    task = policy.prompt_tasks()[0]
    policy.set_prompt(policy.task_prompt(task, seed=3))
    plain, _ = _episode(policy, task, 5)
    for kind in KINDS:
        a = policy.adapt(task, kind, seed=3, steps=3, batch=4, lr=1e-2)
        assert a.kind == kind and a.task == task and repr(a).startswith("Adaptation(")
        log = a.log
        assert log["steps"] == 3 and log["trainable"] > 0 and np.isfinite(log["loss_after"])
        again = policy.adapt(task, kind, seed=3, steps=3, batch=4, lr=1e-2).log
        assert {k: v for k, v in again.items() if k != "seconds"} == {
            k: v for k, v in log.items() if k != "seconds"
        }
        policy.set_prompt(a)
        adapted, ret = _episode(policy, task, 5)
        assert np.isfinite(ret) and adapted.shape == plain.shape
        # the adapted policy is not the plain one (step 0 of every adaptation is)
        assert not np.array_equal(adapted, plain), kind
        # the same adaptation acts the same way again
        assert np.array_equal(_episode(policy, task, 5)[0], adapted)
    # A plain prompt set afterwards drops LoRA's adapters: the plain actions again.
    policy.set_prompt(policy.task_prompt(task, seed=3))
    assert np.array_equal(_episode(policy, task, 5)[0], plain)


def test_bad_adaptations_are_refused_by_name(point_run):
    policy = promptdt.Policy.load(point_run, threads=1)
    task = policy.prompt_tasks()[0]
    with pytest.raises(ValueError, match="unknown adaptation `finetune`"):
        policy.adapt(task, "finetune")
    with pytest.raises(ValueError, match="name an adaptation"):
        policy.adapt(task, "none")
    with pytest.raises(ValueError, match="one prompt per task"):
        policy.adapt(task, "lora", prompt_strategy="bandit")
    with pytest.raises(ValueError, match="eval.adapt.steps = 0"):
        policy.adapt(task, "lora", steps=0)
    with pytest.raises(ValueError, match="task 999"):
        policy.adapt(999, "lora")
    other = promptdt.Policy.load(point_run, threads=1)
    with pytest.raises(ValueError, match="another Policy"):
        other.set_prompt(policy.adapt(task, "lora", steps=1))
    with pytest.raises(ValueError, match="unknown adaptation `tune`"):
        promptdt.evaluate(point_run, episodes=1, adapt="tune")
