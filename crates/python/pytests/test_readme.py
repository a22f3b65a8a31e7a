"""The README's Python example runs as written (the demo run is this suite's tiny run)."""
import os
import re
import subprocess
import sys


def test_readme_example_runs_as_written(repo, point_run, tmp_path):
    text = (repo / "README.md").read_text()
    m = re.search(r"<!-- python-example[^>]*-->\n```python\n(.*?)```", text, re.S)
    assert m, "README has no python example"
    code = m.group(1)
    assert len(code.strip().splitlines()) <= 15
    # The example's paths, relative to a checkout: runs/demo/prompt-dt-seed0 and ../shared.
    work = tmp_path / "checkout"
    (work / "runs/demo").mkdir(parents=True)
    os.symlink(point_run, work / "runs/demo/prompt-dt-seed0")
    shared = repo.parent / "shared"
    if shared.exists():
        os.symlink(shared, tmp_path / "shared")
    else:  # without ../shared, a native prompt file stands in for the reference pickle
        import pytest

        pytest.skip("../shared is not beside the checkout")
    out = subprocess.run([sys.executable, "-c", code], cwd=work, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "Cheetah-Vel demonstrations" in out.stdout
    assert "returns of 5 episodes:" in out.stdout
