"""The environment worker: a user's gymnasium environments, made and stepped for promptdt.

``python -m promptdt.worker`` is started by promptdt (the ``promptdt`` command, ``reproduce``)
for a task suite whose ``[environment]`` table names a gymnasium id or a ``module:callable``:
it reads requests on stdin and answers on stdout, one request per vector reset or step of all the
episodes running together (docs/your-own-tasks.md). Each request is
answered by a :class:`Session`, which an evaluation in the calling process (a factory given from
Python) uses too, so both ways of evaluating run the same code on the same numbers.

Framing, both ways: a line of JSON (the header), then, when the header has ``"payload": n``,
``n`` little-endian float32 values as raw bytes. Requests: ``init`` (the spec, one task per
environment, the family's sizes), ``reset`` (``seeds``: one per environment, ``null`` where it is
not reset), ``step`` (``slots``, and their actions in the payload). Replies: ``error`` (with the
``slot`` it is about) for a failure of the request, else the answer (``slots``, the flags, and
the observations then the rewards in the payload).

A collection (``promptdt collect --policy``, ``promptdt.collect(policy=...)``) also names its
policies in ``init`` (``policies``: a name, ``expert`` or ``medium``, to a ``module:callable``,
or to ``null`` for the callable the :class:`Session` was given) and asks, with ``act`` in a
``reset`` or ``step`` (one policy name or ``null`` per environment), for the named policy's action
on each new observation: the reply lists the environments acted for in ``acted`` and appends
their actions to the payload, and ``policy_errors`` (``[slot, message]``) where the policy raised
or returned an action of another size. The policy is called here, beside its environment, so a
vector step stays one request.
"""
from __future__ import annotations

import importlib
import json
import os
import signal
import sys
import traceback
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

PROTOCOL = 1


class WorkerError(Exception):
    """A request that cannot be answered; ``slot`` is the environment it is about, if one."""

    def __init__(self, message: str, slot: Optional[int] = None):
        super().__init__(message)
        self.slot = slot


def _last_line(exc: BaseException) -> str:
    """The last line of an exception's traceback (``ValueError: g must be positive``)."""
    lines = traceback.format_exception_only(type(exc), exc)
    return lines[-1].strip() if lines else repr(exc)


def _task_label(task: Dict[str, Any]) -> str:
    return f"{task.get('name')} (task {task.get('index')})"


def resolve_callable(entry: str) -> Any:
    """The object a ``module:callable`` names (``module:Class.attr`` reaches into the module)."""
    module, _, name = entry.partition(":")
    if not module or not name:
        raise ValueError(f"`{entry}` is not of the form module:callable")
    target: Any = importlib.import_module(module)
    for part in name.split("."):
        target = getattr(target, part)
    return target


def factory_from_spec(spec: Dict[str, Any]) -> Callable[[Dict[str, Any]], Any]:
    """``factory(task)`` of a suite's ``[environment]`` table: ``entry`` (a gymnasium id, or a
    ``module:callable``) called with ``kwargs`` and the task's ``params`` (under
    ``task_keyword``, or spread as keyword arguments), after importing ``imports``."""
    for module in spec.get("imports") or []:
        importlib.import_module(module)
    entry = spec["entry"]
    kwargs = dict(spec.get("kwargs") or {})
    keyword = spec.get("task_keyword")
    if ":" in entry:
        make = resolve_callable(entry)
    else:
        import gymnasium

        def make(**kw: Any) -> Any:
            return gymnasium.make(entry, **kw)

    def factory(task: Dict[str, Any]) -> Any:
        params = task.get("params") or {}
        if keyword:
            return make(**kwargs, **{keyword: params})
        if not isinstance(params, dict):
            raise TypeError(f"params {params!r} must be a table when there is no task_keyword")
        return make(**kwargs, **params)

    return factory


def _flat_size(space: Any) -> Optional[int]:
    shape = getattr(space, "shape", None)
    return None if shape is None else int(np.prod(shape)) if len(shape) else 1


class Envs:
    """One environment per slot, each made by ``factory(task)`` for its task (a dict with
    ``index``, ``name`` and ``params``), checked against the family's sizes; reset and stepped by
    slot (what a :class:`Session` answers with)."""

    def __init__(self, factory: Callable[[Dict[str, Any]], Any], tasks: Sequence[Dict[str, Any]],
                 obs_dim: int, act_dim: int):
        self.tasks = list(tasks)
        self.obs_dim, self.act_dim = int(obs_dim), int(act_dim)
        #: the collection's policies by name (``init``'s ``policies``); none in an evaluation
        self.policies: Dict[str, Callable[[np.ndarray, Dict[str, Any]], Any]] = {}
        self.envs: List[Any] = []
        made: Dict[int, Any] = {}
        for slot, task in enumerate(self.tasks):
            try:
                env = factory(dict(task))
            except Exception as e:  # the user's code: its error goes back, named
                raise WorkerError(f"making its environment raised {_last_line(e)}", slot) from e
            self._check_spaces(slot, env)
            self.envs.append(env)
            made[id(env)] = env
        if len(made) != len(self.envs):
            raise WorkerError("the factory returned the same environment object for two episodes; "
                              "each call must make a new one")

    def _check_spaces(self, slot: int, env: Any) -> None:
        for what, space, want in (("observation", "observation_space", self.obs_dim),
                                  ("action", "action_space", self.act_dim)):
            got = _flat_size(getattr(env, space, None))
            if got != want:
                shape = getattr(getattr(env, space, None), "shape", None)
                raise WorkerError(
                    f"its environment's {what} space has shape {shape} ({got} values), but the "
                    f"suite declares {want}", slot)

    def _obs(self, slot: int, obs: Any) -> np.ndarray:
        flat = np.asarray(obs, dtype=np.float32).reshape(-1)
        if flat.size != self.obs_dim:
            raise WorkerError(f"its environment returned an observation of {flat.size} values, "
                              f"but the suite declares {self.obs_dim}", slot)
        return flat

    def reset(self, seeds: Sequence[Optional[int]]) -> Tuple[List[int], np.ndarray]:
        """Resets each environment whose seed is not None (``env.reset(seed=seed)``); returns the
        slots reset and their first observations ``[n, obs_dim]``."""
        if len(seeds) != len(self.envs):
            raise WorkerError(f"{len(seeds)} seeds for {len(self.envs)} environments")
        given = [(i, int(s)) for i, s in enumerate(seeds) if s is not None]
        slots = [i for i, _ in given]
        obs = np.zeros((len(slots), self.obs_dim), dtype=np.float32)
        for k, (i, seed) in enumerate(given):
            try:
                first, _info = self.envs[i].reset(seed=seed)
            except Exception as e:
                raise WorkerError(f"its environment's reset raised {_last_line(e)}", i) from e
            obs[k] = self._obs(i, first)
        return slots, obs

    def step(self, slots: Sequence[int], actions: np.ndarray) -> Dict[str, Any]:
        """Steps each environment of ``slots`` with its row of ``actions`` ``[n, act_dim]``.
        Returns the flags per slot, ``errors`` (``[slot, message]`` where ``step`` raised; that
        row is zeros), ``obs`` ``[n, obs_dim]`` and ``rewards`` ``[n]`` float32."""
        n = len(slots)
        actions = np.asarray(actions, dtype=np.float32).reshape(n, self.act_dim)
        obs = np.zeros((n, self.obs_dim), dtype=np.float32)
        rewards = np.zeros(n, dtype=np.float32)
        terminated, truncated = [False] * n, [False] * n
        success: List[Optional[bool]] = [None] * n
        errors: List[List[Any]] = []
        for k, i in enumerate(slots):
            env = self.envs[i]
            dtype = getattr(env.action_space, "dtype", None)
            action = actions[k] if dtype is None else actions[k].astype(dtype, copy=False)
            try:
                o, r, term, trunc, info = env.step(action)
            except Exception as e:
                errors.append([i, _last_line(e)])
                continue
            obs[k] = self._obs(i, o)
            rewards[k] = np.float32(r)
            terminated[k], truncated[k] = bool(term), bool(trunc)
            won = info.get("success") if isinstance(info, dict) else None
            success[k] = None if won is None else bool(won)
        return {"slots": list(slots), "terminated": terminated, "truncated": truncated,
                "success": success, "errors": errors, "obs": obs, "rewards": rewards}

    def act(self, slots: Sequence[int], names: Sequence[Optional[str]], obs: np.ndarray
            ) -> Tuple[List[int], np.ndarray, List[List[Any]]]:
        """The named policy's action on each observation row of ``slots`` whose name is not None
        (``policy(obs, task)``, ``obs`` a float32 copy of what the dataset records, ``task`` the
        slot's ``{"index", "name", "params"}``). Returns the slots acted for, their actions
        ``[m, act_dim]`` float32, and ``[slot, message]`` where the policy raised or returned
        something that is not ``act_dim`` numbers (promptdt checks the values themselves)."""
        acted: List[int] = []
        rows: List[np.ndarray] = []
        errors: List[List[Any]] = []
        for k, (i, name) in enumerate(zip(slots, names)):
            if name is None:
                continue
            policy = self.policies.get(name)
            if policy is None:
                raise WorkerError(f"no policy named `{name}` (init named {sorted(self.policies)})", i)
            try:
                a = policy(obs[k].copy(), dict(self.tasks[i]))
            except Exception as e:  # the user's code: its error goes back, named
                errors.append([i, f"the {name} policy raised {_last_line(e)}"])
                continue
            try:
                flat = np.asarray(a, dtype=np.float32).reshape(-1)
            except Exception as e:
                errors.append([i, f"the {name} policy returned {type(a).__name__}, not numbers "
                                  f"({_last_line(e)})"])
                continue
            if flat.size != self.act_dim:
                errors.append([i, f"the {name} policy returned an action of shape "
                                  f"{np.shape(a)} ({flat.size} values), but the suite declares "
                                  f"act_dim = {self.act_dim}"])
                continue
            acted.append(i)
            rows.append(flat)
        actions = np.stack(rows) if rows else np.zeros((0, self.act_dim), dtype=np.float32)
        return acted, actions, errors

    def close(self) -> None:
        for env in self.envs:
            try:
                env.close()
            except Exception:  # closing is best effort: the answers are all in
                pass


def _policies(named: Dict[str, Optional[str]], given: Dict[str, Callable[..., Any]]
              ) -> Dict[str, Callable[..., Any]]:
    """``init``'s ``policies``: each name's ``module:callable`` imported, or (``null``) the
    callable of that name the session was given."""
    out: Dict[str, Callable[..., Any]] = {}
    for name, entry in named.items():
        if entry is None:
            if name not in given:
                raise WorkerError(f"the {name} policy was to be given to the session, and was not")
            out[name] = given[name]
            continue
        try:
            out[name] = resolve_callable(entry)
        except Exception as e:  # an import or a name in --policy
            raise WorkerError(f"the {name} policy `{entry}`: {_last_line(e)}") from e
        if not callable(out[name]):
            raise WorkerError(f"the {name} policy `{entry}` is a {type(out[name]).__name__}, "
                              "not a callable policy(obs, task)")
    return out


def _with_actions(envs: Envs, reply: Dict[str, Any], values: np.ndarray, slots: Sequence[int],
                  names: Optional[Sequence[Optional[str]]], obs: np.ndarray,
                  ended: Sequence[bool]) -> Tuple[Dict[str, Any], np.ndarray]:
    """``reply`` and ``values`` with the policies' actions asked for by ``names`` (one per slot;
    none for a slot whose episode ``ended``) appended: ``acted``, ``policy_errors``, rows."""
    if names is None:
        return reply, values
    if len(names) != len(slots):
        raise WorkerError(f"`act` names {len(names)} policies for {len(slots)} environments")
    names = [None if end else n for n, end in zip(names, ended)]
    acted, actions, errors = envs.act(slots, names, obs)
    reply = dict(reply, acted=acted, policy_errors=errors)
    return reply, np.concatenate([values, actions.reshape(-1)])


def _answer(envs: Optional[Envs], header: Dict[str, Any], payload: np.ndarray,
            factory: Optional[Callable[[Dict[str, Any]], Any]],
            given: Optional[Dict[str, Callable[..., Any]]] = None
            ) -> Tuple[Optional[Envs], Dict[str, Any], Optional[np.ndarray]]:
    op = header.get("op")
    if op == "init":
        if header.get("protocol") != PROTOCOL:
            raise WorkerError(f"protocol {header.get('protocol')} requested, this promptdt "
                              f"worker speaks {PROTOCOL} (install the same promptdt version)")
        spec = header.get("spec")
        if spec is not None:
            try:
                factory = factory_from_spec(spec)
            except Exception as e:  # an import or a name in the suite's entry
                raise WorkerError(f"the environment entry `{spec.get('entry')}`: "
                                  f"{_last_line(e)}") from e
        if factory is None:
            raise WorkerError("`init` without a spec, and no factory was given")
        policies = _policies(header.get("policies") or {}, given or {})
        envs = Envs(factory, header["tasks"], header["obs_dim"], header["act_dim"])
        envs.policies = policies
        return envs, {"ok": True}, None
    if envs is None:
        raise WorkerError(f"`{op}` before `init`")
    act = header.get("act")
    if op == "reset":
        slots, obs = envs.reset(header["seeds"])
        names = None if act is None else [act[i] for i in slots]
        return (envs, *_with_actions(envs, {"slots": slots}, obs.reshape(-1), slots, names, obs,
                                     [False] * len(slots)))
    if op == "step":
        out = envs.step(header["slots"], payload)
        obs = out.pop("obs")
        values = np.concatenate([obs.reshape(-1), out.pop("rewards")])
        failed = {i for i, _ in out["errors"]}
        ended = [t or u or i in failed
                 for t, u, i in zip(out["terminated"], out["truncated"], out["slots"])]
        return (envs, *_with_actions(envs, out, values, out["slots"], act, obs, ended))
    raise WorkerError(f"unknown request `{op}`")


class Session:
    """The Python side of one batch of environments: answers each request (its JSON header text
    and float32 payload) with a reply (header text, float32 payload or None). The worker process
    (:func:`serve`) and an evaluation in the calling process (from Rust, with a factory given in
    Python) both answer through it, so they run the same code on the same numbers. ``factory``
    makes the environments when ``init`` carries no spec; ``policies`` are a collection's
    policies (``{"expert": callable, ...}``) when ``init`` names them without an entry."""

    def __init__(self, factory: Optional[Callable[[Dict[str, Any]], Any]] = None,
                 policies: Optional[Dict[str, Callable[..., Any]]] = None):
        self.factory = factory
        #: a collection's policies by name (``expert``, ``medium``), for an ``init`` that names
        #: them without a ``module:callable``
        self.policies = dict(policies or {})
        self.envs: Optional[Envs] = None

    def handle(self, header: str, payload: Any = None) -> Tuple[str, Optional[np.ndarray]]:
        values: Optional[np.ndarray] = None
        try:
            request = json.loads(header)
            data = np.asarray([] if payload is None else payload, dtype="<f4").reshape(-1)
            self.envs, reply, values = _answer(self.envs, request, data, self.factory,
                                               self.policies)
        except WorkerError as e:
            reply = {"error": str(e), **({} if e.slot is None else {"slot": e.slot})}
        except Exception as e:  # a bug here, or a request this side cannot read
            traceback.print_exc()
            reply = {"error": f"the worker failed: {_last_line(e)}"}
        if values is not None:
            values = np.ascontiguousarray(values, dtype="<f4")
            reply = dict(reply, payload=int(values.size))
        return json.dumps(reply), values

    def close(self) -> None:
        if self.envs is not None:
            self.envs.close()


def serve(inp: Any, out: Any) -> None:
    """Answers requests from ``inp`` on ``out`` (binary streams, in the framing above) until
    ``inp`` ends."""
    session = Session()
    try:
        while True:
            line = inp.readline()
            if not line:
                return
            n = int(json.loads(line).get("payload", 0))
            data = inp.read(4 * n)
            if len(data) != 4 * n:
                raise WorkerError(f"the request announced {n} payload values, which did not come")
            header, values = session.handle(line.decode(), np.frombuffer(data, dtype="<f4"))
            body = b"" if values is None else values.tobytes()
            out.write(header.encode() + b"\n" + body)
            out.flush()
    finally:
        session.close()


def main() -> None:
    # Ctrl-C in a terminal reaches the whole process group: promptdt decides how to stop and then
    # closes this worker (its stdin ends, or it is killed), so the worker must not die first.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The protocol owns the real stdout; whatever the user's code prints (Python or native) goes
    # to stderr, where promptdt keeps the last lines for its error messages.
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    serve(sys.stdin.buffer, out)


if __name__ == "__main__":
    main()
