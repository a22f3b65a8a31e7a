"""The README's Python example runs as written (the demo run is this suite's tiny run)."""
import os
import re
import subprocess
import sys


def test_readme_example_runs_as_written(repo, point_data, point_run, tmp_path):
    text = (repo / "README.md").read_text()
    m = re.search(r"<!-- python-example[^>]*-->\n```python\n(.*?)```", text, re.S)
    assert m, "README has no python example"
    code = m.group(1)
    assert len(code.strip().splitlines()) <= 15
    # The example's paths, relative to a checkout after `make demo`: runs/demo/data (the demo's
    # point-robot datasets) and runs/demo/prompt-dt-seed0. Nothing beside the checkout: a fresh
    # clone has no ../shared, and the example must not need it.
    assert "../shared" not in code
    work = tmp_path / "checkout"
    (work / "runs/demo").mkdir(parents=True)
    os.symlink(point_data, work / "runs/demo/data")
    os.symlink(point_run, work / "runs/demo/prompt-dt-seed0")
    out = subprocess.run([sys.executable, "-c", code], cwd=work, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "5 demonstrations of goal 0" in out.stdout
    assert "returns of 5 episodes:" in out.stdout
