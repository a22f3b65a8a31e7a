#!/usr/bin/env bash
# Installs the built wheel (target/wheels/promptdt-*.whl, cp39-abi3) into a fresh venv of each given
# CPython version and runs a smoke test there, away from the checkout (one abi3 wheel serves them all):
#
#   bash scripts/check_python_versions.sh [VERSION ...]      (default: 3.9 3.10 3.12 3.13)
#
# Each interpreter is taken, in this order, from: python3.X on PATH, pyenv's versions
# ($PYENV_ROOT/versions/3.X.*), or `uv python install 3.X` (uv from PyPI; it downloads CPython
# builds from GitHub, which needs network access to github.com). A version with no interpreter is
# reported and counts as a failure. The venvs get only numpy and gymnasium from PyPI, besides the
# wheel. Prints one line per version and exits non-zero if any failed.
set -uo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
versions=("$@")
[ ${#versions[@]} -gt 0 ] || versions=(3.9 3.10 3.12 3.13)
wheel=$(ls target/wheels/promptdt-*.whl 2>/dev/null | tail -1)
if [ -z "$wheel" ]; then
    echo "check_python_versions: no wheel in target/wheels (bash scripts/install_python.sh builds it)" >&2
    exit 2
fi
wheel="$repo/$wheel"
work=$(mktemp -d "${TMPDIR:-/tmp}/promptdt-pyversions.XXXXXX")
trap 'rm -rf "$work"' EXIT

find_python() {  # $1 = 3.X; prints the interpreter's path
    local v=$1 p
    if p=$(command -v "python$v" 2>/dev/null) && "$p" -c 'import venv' 2>/dev/null; then
        echo "$p"; return 0
    fi
    for p in "${PYENV_ROOT:-$HOME/.pyenv}"/versions/"$v".*/bin/python"$v"; do
        [ -x "$p" ] && { echo "$p"; return 0; }
    done
    local uv
    uv=$(command -v uv 2>/dev/null || true)
    if [ -z "$uv" ]; then
        python3 -m venv "$work/uv" >/dev/null && "$work/uv/bin/pip" install -q uv >/dev/null 2>&1 \
            && uv="$work/uv/bin/uv"
    fi
    if [ -n "$uv" ] && "$uv" python install "$v" --install-dir "$work/pythons" >&2; then
        "$uv" python find "$v" --python-preference only-managed 2>/dev/null \
            || ls "$work"/pythons/cpython-"$v".*/bin/python"$v" 2>/dev/null | head -1
        return 0
    fi
    return 1
}

smoke='
import sys, numpy as np, gymnasium, promptdt
from promptdt.envs import make_vec
assert promptdt.families(), "no families"
env = make_vec("point_robot", tasks=[0, 1], num_envs=2)
obs, _ = env.reset(seed=0)
env.action_space.seed(0)
total = np.zeros(2)
for _ in range(5):
    obs, rew, term, trunc, _ = env.step(env.action_space.sample())
    total += rew
env.close()
assert obs.shape == (2, 2) and np.isfinite(total).all(), (obs.shape, total)
print(f"python {sys.version.split()[0]}: promptdt {promptdt.__version__}, numpy {np.__version__}, "
      f"gymnasium {gymnasium.__version__}: 5 steps of 2 point_robot envs, returns {total.round(3).tolist()}")
'

failed=0
results=()
for v in "${versions[@]}"; do
    start=$SECONDS out=
    if ! py=$(find_python "$v"); then
        results+=("$v: FAILED (no CPython $v found on PATH, in pyenv, or through uv)")
        failed=1
        continue
    fi
    venv="$work/venv-$v"
    if "$py" -m venv "$venv" \
        && "$venv/bin/python" -m pip install -q --disable-pip-version-check "numpy>=1.21" "gymnasium>=1.0,<2" "$wheel" \
        && out=$(cd "$work" && "$venv/bin/python" -c "$smoke" 2>&1); then
        results+=("$v: ok ($py, $((SECONDS - start)) s): ${out##*$'\n'}")
    else
        results+=("$v: FAILED ($py): ${out:-install failed}")
        failed=1
    fi
done
echo "== wheel $(basename "$wheel") in fresh venvs =="
printf '%s\n' "${results[@]}"
exit $failed
