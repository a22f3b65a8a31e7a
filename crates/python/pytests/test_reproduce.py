"""promptdt.experiments() and promptdt.reproduce(): the paper's artifacts from Python, through the
same harness as `promptdt reproduce` (which starts the promptdt binary once per run)."""
import os

import pytest

import promptdt


def test_experiments_list_every_artifact_with_its_budgets():
    names = {e["name"]: e for e in promptdt.experiments()}
    assert {"fig2", "table1", "fig3", "fig4", "appendix_finetune_macaw"} <= names.keys()
    fig2 = names["fig2"]
    assert fig2["cells"] == 28 and fig2["pending"] == 0  # Dial's five cells are in
    budgets = {b["budget"]: b for b in fig2["budgets"]}
    assert budgets["paper"]["iterations"] == 5000 and budgets["smoke"]["iterations"] == 2
    assert "Meta-World reach" in budgets["cpu"]["note"]


def test_reproduce_runs_an_experiment_and_reports_it(repo, tmp_path):
    exe = repo / "target" / "release" / "promptdt"
    if not exe.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{exe} is missing: CI builds it in `make test` before the Python tests")
        pytest.skip("no promptdt binary (cargo build --release -p promptdt)")
    out = tmp_path / "repro"
    with pytest.raises(FileNotFoundError, match="needs the promptdt binary"):
        promptdt.reproduce("fig4", budget="smoke", out=out, exe=tmp_path / "nope")
    with pytest.raises(RuntimeError, match="fig9"):
        promptdt.reproduce("fig9", budget="smoke", out=out, exe=exe)
    r = promptdt.reproduce(
        "fig4", budget="smoke", out=out, jobs=2, exe=exe, pretrained_root=repo / "pretrained"
    )
    assert r["experiment"] == "fig4" and r["budget"] == "smoke"
    assert len(r["cells"]) == 9 and all(c["status"] == "ran" for c in r["cells"])
    assert (out / "reports" / "fig4-smoke" / "report.md").is_file()
    # The runs are finished: the report alone gives the same cells.
    again = promptdt.reproduce("fig4", budget="smoke", out=out, exe=exe, report_only=True)
    assert [c["ours"] for c in again["cells"]] == [c["ours"] for c in r["cells"]]
