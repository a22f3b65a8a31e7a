"""Issue 34, point 10: the installed package's types. `mypy --strict` accepts the README's Python
example, `stubtest` finds the stubs of promptdt._native true to the module, and the gymnasium
env's reset/step are annotated."""
import os
import re
import subprocess
import sys
import typing

import pytest

mypy = pytest.importorskip("mypy")


def run_mypy(args, cwd):
    # Out of the checkout (cwd): mypy reads the installed package, as a user's does.
    env = dict(os.environ, MYPY_CACHE_DIR=str(cwd / ".mypy_cache"))
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, env=env, timeout=600)


def test_mypy_strict_accepts_the_readme_example(repo, tmp_path):
    text = (repo / "README.md").read_text()
    m = re.search(r"<!-- python-example[^>]*-->\n```python\n(.*?)```", text, re.S)
    assert m, "README has no python example"
    (tmp_path / "example.py").write_text(m.group(1))
    out = run_mypy(["mypy", "--strict", "example.py"], tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr


def test_stubtest_finds_the_stubs_true_to_the_module(tmp_path):
    out = run_mypy(["mypy.stubtest", "promptdt._native"], tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr


def test_vector_env_reset_and_step_are_annotated():
    from promptdt.envs import PromptDTEnv, PromptDTVectorEnv

    for cls in (PromptDTVectorEnv, PromptDTEnv):
        for name in ("reset", "step"):
            hints = typing.get_type_hints(getattr(cls, name))
            assert "return" in hints and typing.get_origin(hints["return"]) is tuple, (cls, name)


def test_mypy_strict_accepts_minari_calls_and_star_imports(tmp_path):
    """Issue 56: export_minari/import_minari were untyped `*args, **kwargs` wrappers (an error
    under --strict), and `make_vec` was not in `__all__`."""
    (tmp_path / "user.py").write_text(
        "from pathlib import Path\n"
        "from typing import List\n"
        "import promptdt\n"
        "from promptdt import *\n"
        "\n"
        "def export(data: Path) -> List[Path]:\n"
        "    ds = promptdt.export_minari(data, 'promptdt/point_robot/x-v0', tasks=[1, 2])\n"
        "    return promptdt.import_minari(ds, data / 'back', env='point_robot')\n"
        "\n"
        "env = make_vec('point_robot', 2, task=0)\n"
        "files: List[Path] = import_minari('promptdt/point_robot/x-v0', 'out')\n"
    )
    out = run_mypy(["mypy", "--strict", "user.py"], tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr


def test_mypy_finds_the_package_consistent(tmp_path):
    """The package's own modules, as installed: a name imported from a sibling module must exist
    (minari_io imported `envs.gym_id`, which never did, behind an ImportError fallback)."""
    out = run_mypy(["mypy", "-p", "promptdt"], tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr


def test_make_vec_is_exported():
    import promptdt

    assert "make_vec" in promptdt.__all__
    names: dict = {}
    exec("from promptdt import *", names)
    assert names["make_vec"] is promptdt.envs.make_vec
