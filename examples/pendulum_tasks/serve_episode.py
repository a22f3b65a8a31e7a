"""Serves a run (`promptdt serve`) and plays one episode of a held-out task through its HTTP API
(docs/serve.md) in this process's environment, `tasks.make`'s; then stops the server:

    python serve_episode.py RUN [--promptdt PATH]

The server draws the episode's prompt from the run's prompt set of the task, as `promptdt eval`
does; a deployed policy would send its own demonstration instead (`"prompt": {...}`).
"""
import argparse
import json
import os
import pathlib
import subprocess
import urllib.request

import numpy as np

from tasks import make

try:
    import tomllib  # Python 3.11+
except ImportError:  # the package supports 3.9
    import tomli as tomllib


def call(url, method, path, body=None):
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url + path, data=data, method=method,
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=60) as r:
        text = r.read().decode()
        return json.loads(text) if text else None


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=pathlib.Path)
    p.add_argument("--promptdt", default=os.environ.get("PROMPTDT_BIN", "promptdt"))
    a = p.parse_args()
    # Port 0: the system picks a free port, and the server says which on its first line.
    server = subprocess.Popen([a.promptdt, "serve", "--run", str(a.run), "--listen", "127.0.0.1:0"],
                              stdout=subprocess.PIPE, text=True)
    try:
        line = server.stdout.readline().strip()
        if not line.startswith("listening on "):
            raise SystemExit(f"promptdt serve did not start: {line!r}")
        url = line.removeprefix("listening on ")
        info = call(url, "GET", "/v1/info")
        task = info["prompt_tasks"][0]  # the first held-out task
        suite = tomllib.loads((a.run / "suite.toml").read_text())  # the run's copy of the suite
        params = suite["tasks"][task]["params"]
        env = make(params)
        obs, _ = env.reset(seed=0)
        reply = call(url, "POST", "/v1/episodes", {"task": task, "observation": obs.tolist()})
        episode, total, steps = reply["episode"], 0.0, 0
        while True:
            action = np.clip(np.asarray(reply["action"], np.float32), -2.0, 2.0)
            obs, reward, terminated, truncated, _ = env.step(action)
            total, steps = total + float(reward), steps + 1
            if terminated or truncated or steps == suite["max_ep_len"]:
                break
            reply = call(url, "POST", f"/v1/episodes/{episode}/step",
                         {"reward": float(reward), "observation": obs.tolist()})
        call(url, "DELETE", f"/v1/episodes/{episode}")
        print(f"served {info['method']} (iteration {info['iteration']}): one episode of task {task} "
              f"{params}, {steps} steps, return {total:.2f}")
    finally:
        server.terminate()
        server.wait(timeout=30)


if __name__ == "__main__":
    main()
