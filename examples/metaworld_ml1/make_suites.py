"""Writes the example's suite files, {push-v3,pick-place-v3}.toml beside it (committed; run again after
changing what is below). Each suite is ML1's 50 goals of one Meta-World environment
(``ML1(env_name, seed=1)``: the seed the paper's reach-v2 tasks come from), goals 0-44 for training
and 45-49 held out (ML1 draws its goals at random, so the last five are as good a held-out set as any).
"""
from pathlib import Path

HERE = Path(__file__).resolve().parent

# rtg_scale and target_return, from the expert data (collect.py's defaults, its dataset.json): on
# push-v3 the 50 goals' expert episodes return 3737 on average (per goal from 1101 to 4640), the best
# 4660. Returns-to-go are divided by 1000 (values of a few units, as the built-in families' are), and
# evaluation asks for 4700, just above the best expert return (as the reference asks its families for
# about their best returns). pick-place-v3's expert returns as much: 4123 on average (per goal from
# 1355 to 4522), the best 4583, so it gets the same.
SUITES = {
    "push-v3": dict(name="ml1_push", rtg_scale=1000.0, target_return=4700.0),
    "pick-place-v3": dict(name="ml1_pick_place", rtg_scale=1000.0, target_return=4700.0),
}
GOALS, TEST = 50, range(45, 50)


def suite(env_name: str, name: str, rtg_scale: float, target_return: float) -> str:
    tasks = [f"goal-{i}" for i in range(GOALS)]
    train = [t for i, t in enumerate(tasks) if i not in TEST]
    test = [tasks[i] for i in TEST]
    lines = [
        f"# Meta-World ML1 {env_name}: its 50 goal variations (ML1(\"{env_name}\", seed=1).train_tasks),",
        "# goal hidden from the observation. Written by make_suites.py; see docs/your-own-tasks.md.",
        f'name = "{name}"',
        "obs_dim = 39",
        "act_dim = 4",
        "action_bound = 1.0",
        "max_ep_len = 500           # Meta-World's max_path_length",
        f"rtg_scale = {rtg_scale}",
        f"target_return = {target_return}",
        "prompt_length = 5",
        "render_fps = 80           # Meta-World's metadata (frame_skip 5 at dt 0.0025)",
        "",
        "[splits.default]",
        "train = [" + ", ".join(f'"{t}"' for t in train) + "]",
        "test = [" + ", ".join(f'"{t}"' for t in test) + "]",
        "",
        "# promptdt's worker makes each goal's environment: mw_envs.make(env_name=..., ml1_seed=...,",
        "# task=params). Meta-World's info[\"success\"] is the success the evaluations record.",
        "[environment]",
        'entry = "mw_envs:make"',
        'task_keyword = "task"',
        f'kwargs = {{ env_name = "{env_name}", ml1_seed = 1 }}',
        'python = ".venv/bin/python"   # setup.sh makes it',
        "step_timeout_s = 300       # the first environment of a process builds ML1 (seconds)",
        "",
    ]
    for i, t in enumerate(tasks):
        lines += ["[[tasks]]", f'name = "{t}"', f"params = {{ goal = {i} }}", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    for env_name, s in SUITES.items():
        path = HERE / f"{env_name}.toml"
        path.write_text(suite(env_name, **s))
        print(f"wrote {path}")
