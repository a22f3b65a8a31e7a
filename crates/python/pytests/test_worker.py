"""Issue 53 item 3: the environment worker's Python side (``promptdt.worker``), spoken to over
in-memory streams in its own framing: a gymnasium id made per task with the task's parameters,
reset with the given seeds and stepped to gymnasium's own numbers; a factory that raises and wrong
spaces answered as errors naming the environment; a step that raises named in its slot. (The Rust
side, with a real worker process: crates/envs/tests/it/worker.rs.)"""
import io
import json

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from promptdt import worker  # noqa: E402


def frames(*requests):
    out = b""
    for header, payload in requests:
        data = b"" if payload is None else np.asarray(payload, "<f4").tobytes()
        if payload is not None:
            header = dict(header, payload=len(data) // 4)
        out += json.dumps(header).encode() + b"\n" + data
    return io.BytesIO(out)


def replies(buf):
    stream, out = io.BytesIO(buf.getvalue()), []
    while True:
        line = stream.readline()
        if not line:
            return out
        header = json.loads(line)
        n = header.get("payload", 0)
        out.append((header, np.frombuffer(stream.read(4 * n), "<f4")))


def init(entry, tasks, obs_dim=3, act_dim=1, **spec):
    spec = {"entry": entry, "task_keyword": None, "kwargs": {}, "imports": [], **spec}
    return {"op": "init", "protocol": 1, "spec": spec, "tasks": tasks, "obs_dim": obs_dim,
            "act_dim": act_dim}, None


def test_pendulum_through_the_protocol_is_gymnasium_itself():
    tasks = [{"index": 0, "name": "g9", "params": {"g": 9.0}}, {"index": 1, "name": "g4", "params": {"g": 4.0}}]
    actions = np.array([0.5, -1.25], np.float32)
    out = io.BytesIO()
    worker.serve(frames(init("Pendulum-v1", tasks), ({"op": "reset", "seeds": [3, 4]}, None),
                        ({"op": "step", "slots": [0, 1]}, actions)), out)
    (ok, _), (reset, first), (step, values) = replies(out)
    assert ok == {"ok": True} and reset["slots"] == [0, 1] and step["slots"] == [0, 1]
    for i, (g, seed) in enumerate([(9.0, 3), (4.0, 4)]):
        env = gym.make("Pendulum-v1", g=g)
        o, _ = env.reset(seed=seed)
        assert first[3 * i:3 * i + 3].tobytes() == np.asarray(o, np.float32).tobytes()
        o, r, term, trunc, _ = env.step(actions[i:i + 1])
        assert values[3 * i:3 * i + 3].tobytes() == np.asarray(o, np.float32).tobytes()
        assert values[6 + i] == np.float32(r)
        assert (step["terminated"][i], step["truncated"][i], step["success"][i]) == (term, trunc, None)


class Boom(gym.Env):
    observation_space = gym.spaces.Box(-1, 1, (3,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def __init__(self, g=1.0):
        if g < 0:
            raise ValueError(f"g must be positive, got {g}")

    def reset(self, seed=None, options=None):
        return np.zeros(3, np.float32), {}

    def step(self, action):
        raise RuntimeError("the physics broke")


def test_bad_factories_spaces_and_steps_are_named():
    tasks = [{"index": 0, "name": "ok", "params": {"g": 1.0}}, {"index": 5, "name": "bad", "params": {"g": -1.0}}]
    out = io.BytesIO()
    worker.serve(frames(init(f"{__name__}:Boom", tasks)), out)
    (err, _), = replies(out)
    assert err["slot"] == 1 and "ValueError: g must be positive, got -1.0" in err["error"]

    out = io.BytesIO()
    worker.serve(frames(init("Pendulum-v1", tasks[:1], obs_dim=4)), out)
    (err, _), = replies(out)
    assert err["slot"] == 0 and "observation space has shape (3,)" in err["error"] and "declares 4" in err["error"]

    out = io.BytesIO()
    worker.serve(frames(init("no_such_module:make", tasks[:1])), out)
    (err, _), = replies(out)
    assert "no_such_module:make" in err["error"] and "ModuleNotFoundError" in err["error"]

    out = io.BytesIO()
    worker.serve(frames(init(f"{__name__}:Boom", tasks[:1]), ({"op": "reset", "seeds": [1]}, None),
                        ({"op": "step", "slots": [0]}, [0.0])), out)
    _, _, (step, values) = replies(out)
    assert step["errors"] == [[0, "RuntimeError: the physics broke"]] and len(values) == 4


def test_a_request_out_of_protocol_is_an_error_not_a_crash():
    out = io.BytesIO()
    worker.serve(frames(({"op": "step", "slots": [0]}, [0.0]), ({"op": "init", "protocol": 99}, None)), out)
    (first, _), (second, _) = replies(out)
    assert "`step` before `init`" in first["error"]
    assert "protocol 99 requested" in second["error"]


def test_a_session_with_a_factory_answers_as_the_worker_does():
    """In-process (``evaluate(env=factory)``), the same session answers with the factory's
    environments: the numbers are the worker's, bit for bit."""
    tasks = [{"index": 2, "name": "g6", "params": {"g": 6.0}}]
    requests = [init("Pendulum-v1", tasks), ({"op": "reset", "seeds": [11]}, None),
                ({"op": "step", "slots": [0]}, [0.75])]
    out = io.BytesIO()
    worker.serve(frames(*requests), out)
    through_worker = replies(out)
    session = worker.Session(factory=lambda task: gym.make("Pendulum-v1", **task["params"]))
    in_process = []
    for header, payload in requests:
        if header["op"] == "init":
            header = dict(header, spec=None)
        if payload is not None:
            header = dict(header, payload=len(payload))
        text, values = session.handle(json.dumps(header), payload)
        in_process.append((json.loads(text), np.zeros(0, "<f4") if values is None else values))
    for (a, x), (b, y) in zip(through_worker, in_process):
        assert a == b and x.tobytes() == y.tobytes()
    assert "no factory" in worker.Session().handle(json.dumps(dict(requests[0][0], spec=None)))[0]
