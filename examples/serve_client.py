#!/usr/bin/env python3
"""A client of `promptdt serve` (docs/serve.md), Python standard library only.

It drives one episode of a point robot simulated here (position += action clipped to 0.1 per
coordinate; reward = -distance to the goal; 20 steps), asking the server for every action:

    promptdt serve --run runs/prompt-dt-point_robot-seed0 --listen 127.0.0.1:8000 &
    python3 examples/serve_client.py --url http://127.0.0.1:8000 --task 34

The prompt is the one the server draws for `--task` from the run's data, as `promptdt eval` does;
a deployed policy would instead send its own demonstration as arrays (`"prompt": {...}`).

A server started with a token (`--token-file`, `--generate-token` or PROMPTDT_SERVE_TOKEN; needed on
any address but loopback) wants it on every request: give it the same way, `--token-file FILE` or
PROMPTDT_SERVE_TOKEN.
"""
import argparse
import json
import math
import os
import urllib.error
import urllib.request


TOKEN = None


def call(url, method, path, body=None):
    data = None if body is None else json.dumps(body).encode()
    headers = {"Content-Type": "application/json"}
    if TOKEN:
        headers["Authorization"] = f"Bearer {TOKEN}"
    req = urllib.request.Request(url + path, data=data, method=method, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            text = r.read().decode()
            return json.loads(text) if text else None
    except urllib.error.HTTPError as e:
        raise SystemExit(f"{method} {path}: {e.code} {e.read().decode()}")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--url", default="http://127.0.0.1:8000")
    p.add_argument("--task", type=int, default=34, help="point_robot task (goal angle pi*task/39)")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--token-file", help="the server's bearer token (default: PROMPTDT_SERVE_TOKEN)")
    a = p.parse_args()
    global TOKEN
    if a.token_file:
        with open(a.token_file) as f:
            TOKEN = f.read().strip()
    else:
        TOKEN = os.environ.get("PROMPTDT_SERVE_TOKEN")
    info = call(a.url, "GET", "/v1/info")
    print(f"serving {info['method']} (iteration {info['iteration']}), K = {info['k']}")
    angle = math.pi * a.task / 39
    goal = (math.cos(angle), math.sin(angle))
    pos = [0.0, 0.0]
    reply = call(a.url, "POST", "/v1/episodes", {"task": a.task, "observation": pos})
    episode, total = reply["episode"], 0.0
    for t in range(a.steps):
        action = [max(-0.1, min(0.1, x)) for x in reply["action"]]
        pos = [pos[0] + action[0], pos[1] + action[1]]
        reward = -math.hypot(pos[0] - goal[0], pos[1] - goal[1])
        total += reward
        if t + 1 == a.steps:
            break
        reply = call(a.url, "POST", f"/v1/episodes/{episode}/step",
                     {"reward": reward, "observation": pos})
    call(a.url, "DELETE", f"/v1/episodes/{episode}")
    print(f"episode return {total:.3f}, final position ({pos[0]:.3f}, {pos[1]:.3f}), "
          f"goal ({goal[0]:.3f}, {goal[1]:.3f})")


if __name__ == "__main__":
    main()
