#!/usr/bin/env bash
# Makes the example's own virtual environment: Meta-World from PyPI (pinned) with what it needs
# (gymnasium, and the mujoco Python bindings it pins), and the promptdt wheel, so that promptdt's
# worker (`python -m promptdt.worker`) can make Meta-World's environments. Idempotent.
#
#   bash examples/metaworld_ml1/setup.sh [VENV]     (default examples/metaworld_ml1/.venv)
#
# The promptdt wheel: PROMPTDT_WHEEL=path/to/promptdt-*.whl installs that one; otherwise
# scripts/install_python.sh builds it from this checkout and installs it (minutes, once).
# PYTHON picks the interpreter (Meta-World 3.1.1 needs Python 3.10 to 3.13). A promptdt already in
# VENV is kept: after updating the checkout, remove VENV (or pip-install the new wheel) so that the
# worker speaks the `promptdt` binary's protocol (it refuses another, saying so).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
venv="${1:-$here/.venv}"
python="${PYTHON:-python3}"

# Meta-World 3.1.1 (the newest release on PyPI) pins mujoco==3.3.0 (the Python bindings; promptdt's
# own MuJoCo 3.17 lives in its wheel under another soname, so both load in one process).
METAWORLD="metaworld==3.1.1"

if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install -q --disable-pip-version-check "$METAWORLD" "gymnasium>=1.1,<2" "numpy>=1.21" \
    packaging  # gymnasium.envs.mujoco imports it, and gymnasium does not declare it

if ! "$venv/bin/python" -c "import promptdt" 2>/dev/null; then
    if [ -n "${PROMPTDT_WHEEL:-}" ]; then
        "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps "$PROMPTDT_WHEEL"
    else
        (cd "$root" && bash scripts/install_python.sh "$venv")
    fi
fi
"$venv/bin/python" - <<'PY'
import metaworld, mujoco, gymnasium, promptdt
print(f"setup: metaworld {metaworld.__version__ if hasattr(metaworld, '__version__') else '?'}, "
      f"mujoco {mujoco.__version__}, gymnasium {gymnasium.__version__}, promptdt {promptdt.__version__}")
PY
