"""promptdt.collect from Python: the count it returns is the files it wrote, unknown families are
named, and the MuJoCo families collect from the agents shipped in the wheel (from any directory)."""
import pathlib

import pytest

import promptdt


def test_collect_from_shipped_agents_counts_its_files(tmp_path, monkeypatch):
    # Away from the checkout: the default agents are the wheel's, not ./pretrained.
    monkeypatch.chdir(tmp_path)
    agents = pathlib.Path(promptdt.__file__).parent / "pretrained"
    assert (agents / "cheetah_vel" / "agent.json").is_file()
    assert promptdt.pretrained_dir("cheetah_vel") == agents / "cheetah_vel"
    out = tmp_path / "cv"
    n = promptdt.collect("cheetah_vel", out, episodes=1, prompt_episodes=1, progress=False)
    files = sorted(out.glob("*.safetensors"))
    assert n == len(files) == 40 * 3 * 2
    ds = promptdt.load_dataset(out / "cheetah_vel-7-prompt-medium.safetensors")
    assert (ds.env, ds.task, ds.mode, len(ds)) == ("cheetah_vel", 7, "prompt-medium", 1)


def test_collect_scripted_counts_its_files(tmp_path):
    out = tmp_path / "pr"
    n = promptdt.collect("point_robot", out, episodes=2, prompt_episodes=1, progress=False)
    assert n == len(list(out.glob("*.safetensors"))) == 40 * 3 * 2


def test_collect_names_an_unknown_family(tmp_path):
    with pytest.raises(ValueError, match=r"unknown environment `nope` \(known: .*cheetah_vel.*\)"):
        promptdt.collect("nope", tmp_path / "x")
    with pytest.raises(ValueError, match="agent directory"):
        promptdt.pretrained_dir("point_robot")  # scripted: it has no agent
    assert not (tmp_path / "x").exists()
