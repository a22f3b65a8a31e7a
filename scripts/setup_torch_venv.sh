#!/usr/bin/env bash
# Installs PyTorch 2.11.0 (CPU use, no CUDA wheels) into .venv, following the recipe in
# scripts/requirements-torch.txt. Idempotent: does nothing when .venv already imports that torch.
# Used by `.ci/run` (so CI checks parity with PyTorch bit for bit on whatever CPU it gets) and by
# anyone who wants the same check from `make test`, or `promptdt bench` side by side with PyTorch.
#
#   bash scripts/setup_torch_venv.sh [VENV_DIR]      (default .venv; PYTHON picks the interpreter)
#
# Cost, measured on the 2-core CI machine kind: about 35 s with an empty pip cache (530 MB torch
# wheel), 1.4 GB on disk.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${1:-.venv}"
python="${PYTHON:-python3}"
want="2.11.0"
if "$venv/bin/python" -c "import torch, numpy, safetensors, sys; sys.exit(0 if torch.__version__.split('+')[0] == '$want' else 1)" 2>/dev/null; then
    echo "setup_torch_venv: $venv already has torch $want"
    exit 0
fi
start=$(date +%s)
"$python" -m venv "$venv"
"$venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps -r scripts/requirements-torch.txt
sed -n 's/^#| \{0,1\}//p' scripts/requirements-torch.txt | "$venv/bin/python" -
"$venv/bin/python" -c "import torch; print('setup_torch_venv: torch', torch.__version__, 'kernels', torch.backends.cpu.get_cpu_capability())"
echo "setup_torch_venv: done in $(( $(date +%s) - start )) s"
