"""What the wheel is, as installed: its tag (abi3) and the licences it carries (one wheel for every
CPython from 3.9, and the licences of everything it bundles)."""
import email
import importlib.metadata
import pathlib
import zipfile

import pytest

import promptdt

REPO = pathlib.Path(__file__).resolve().parents[3]
PACKAGE = pathlib.Path(promptdt.__file__).resolve().parent

# Each library bundled in promptdt/_libs -> the _licenses/ folder with its licence texts, and the
# files that folder must hold.
BUNDLED = {
    "libtorch_cpu.so": "torch",
    "libc10.so": "torch",
    "libgomp.so.1": "libgomp",
    "libcudart.so.13": "nvidia-cuda-runtime",
    "libcupti.so.13": "nvidia-cuda-cupti",
    "libmujoco.so.3.17.0": "mujoco",
}
LICENCE_FILES = {
    "promptdt": ["LICENSE"],
    "torch": ["LICENSE", "NOTICE"],
    "libgomp": ["COPYING3", "COPYING.RUNTIME"],
    "nvidia-cuda-runtime": ["License.txt"],
    "nvidia-cuda-cupti": ["License.txt"],
    "mujoco": ["LICENSE", "LICENSES_THIRD_PARTY.md"],
}
# A phrase of each text, so that a wrong or empty file is caught too.
PHRASES = {
    ("promptdt", "LICENSE"): "MIT License",
    ("torch", "LICENSE"): "Redistribution and use in source and binary forms",
    ("libgomp", "COPYING3"): "GNU GENERAL PUBLIC LICENSE",
    ("libgomp", "COPYING.RUNTIME"): "GCC RUNTIME LIBRARY EXCEPTION",
    ("nvidia-cuda-runtime", "License.txt"): "NVIDIA",
    ("mujoco", "LICENSE"): "Apache License",
}
EXPRESSION_PARTS = ["MIT", "BSD-3-Clause", "Apache-2.0", "GPL-3.0-or-later WITH GCC-exception-3.1",
                    "LicenseRef-NVIDIA-Proprietary"]


def expected_paths():
    return [f"{folder}/{name}" for folder, names in LICENCE_FILES.items() for name in names]


def dist():
    return importlib.metadata.distribution("promptdt")


def test_wheel_is_abi3_for_python_3_9_and_later():
    wheel = email.message_from_string(dist().read_text("WHEEL"))
    tags = wheel.get_all("Tag")
    assert tags == ["cp39-abi3-linux_x86_64"], tags
    assert wheel["Root-Is-Purelib"] == "false"
    # The module file is named for the stable ABI, not for one CPython version.
    native = [p.name for p in PACKAGE.iterdir() if p.name.startswith("_native.") and p.suffix == ".so"]
    assert native == ["_native.abi3.so"], native


def test_every_bundled_library_has_its_licence_installed_beside_it():
    libs = sorted(p.name for p in (PACKAGE / "_libs").iterdir())
    assert libs == sorted(BUNDLED), f"_libs holds {libs}: give each new library its licence"
    for folder in set(BUNDLED.values()) | {"promptdt"}:
        for name in LICENCE_FILES[folder]:
            path = PACKAGE / "_licenses" / folder / name
            assert path.is_file() and path.stat().st_size > 0, path
            phrase = PHRASES.get((folder, name))
            if phrase:
                assert phrase in path.read_text(encoding="utf-8", errors="replace"), (path, phrase)


def test_metadata_names_the_licences_and_lists_their_files():
    meta = dist().metadata
    expression = meta["License-Expression"]
    assert expression, "no License-Expression (PEP 639) in the metadata"
    for part in EXPRESSION_PARTS:
        assert part in expression, (part, expression)
    listed = meta.get_all("License-File") or []
    for path in expected_paths():
        assert any(f.endswith("_licenses/" + path) for f in listed), (path, listed)
    # .dist-info/licenses/ holds them (PEP 639), as `pip show -f` lists them.
    files = [str(f) for f in dist().files or []]
    for path in expected_paths():
        assert any(".dist-info/licenses/" in f and f.endswith("_licenses/" + path) for f in files), path


def wheel_file():
    wheels = sorted((REPO / "target" / "wheels").glob("promptdt-*.whl"))
    if not wheels:
        pytest.skip("no wheel in target/wheels (installed from elsewhere)")
    return wheels[-1]


def test_unzip_of_the_wheel_lists_every_licence():
    wheel = wheel_file()
    assert "-cp39-abi3-" in wheel.name, wheel.name
    names = zipfile.ZipFile(wheel).namelist()
    for path in expected_paths():
        assert f"promptdt/_licenses/{path}" in names, path
        assert any(n.endswith(f".dist-info/licenses/python/promptdt/_licenses/{path}") for n in names), path


def test_train_evaluate_collect_need_no_gymnasium(tmp_path):
    """gymnasium is optional (pyproject: the `gym` extra): the argument checks of train, evaluate
    and collect imported promptdt.envs, which needs it (ImportError for `seed=1`)."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['gymnasium'] = None\n"
            "import promptdt\n"
            "assert not hasattr(promptdt, 'make_vec') and 'make_vec' not in promptdt.__all__\n"
            f"n = promptdt.collect('point_robot', {str(tmp_path / 'd')!r}, seed=1, episodes=1, "
            "prompt_episodes=1, progress=False)\n"
            "assert n == 240, n\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
