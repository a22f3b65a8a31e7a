#!/usr/bin/env bash
# Builds the promptdt Python package (a wheel, with maturin) and installs it into a virtual
# environment, from a clean clone, idempotently:
#
#   bash scripts/install_python.sh [VENV]        (default .venv-promptdt; PYTHON picks the interpreter)
#   VENV/bin/python -c "import promptdt"
#
# What it does:
#   1. fetches libtorch 2.11.0 (CPU part), MuJoCo 3.17.0 and Meta-World's reach scene into
#      third_party/ if they are not there (the same scripts as `make setup`);
#   2. creates VENV if needed and installs the build and test tools in it (maturin, numpy,
#      gymnasium, pytest, safetensors; minari with PROMPTDT_PY_EXTRAS=minari);
#   3. copies the shared libraries the module links (libtorch_cpu, libc10, libgomp, the CUDA runtime
#      and CUPTI stubs libtorch_cpu names, libmujoco) into promptdt/_libs, where the module's
#      $ORIGIN/_libs rpath finds them: the wheel is self-contained (no torch, no environment
#      variables), and it does not depend on this checkout once installed;
#   4. copies the licence texts of the project and of each bundled library into promptdt/_licenses
#      (the wheel also lists them in its .dist-info/licenses, see pyproject.toml), and the trained
#      agents (pretrained/) into promptdt/pretrained, the `collect` default;
#   5. builds the wheel into target/wheels (release, stripped; one cp39-abi3 wheel for CPython 3.9+)
#      and pip-installs it into VENV.
#
# The build reuses target/: the library crates are built with the same features as by `make test`
# and `make demo` (crates/testkit/tests/it/one_build.rs), so after either only pyo3 and the extension
# are compiled, and a second run after a change only rebuilds the extension. Cost and wheel size:
# see docs/python.md.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${1:-.venv-promptdt}"
python="${PYTHON:-python3}"
start=$(date +%s)

python3 scripts/fetch_libtorch.py
python3 scripts/fetch_mujoco.py
# Also Meta-World's reach scene, as `make setup` does. pdt-envs' build script would fetch it itself,
# but it watches the file the fetch creates: the next cargo build (`make demo`, `make test`) would
# then run it again and rebuild pdt-envs and the eight crates above it.
python3 scripts/fetch_metaworld.py

if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi
pkgs=("maturin>=1.9.4,<2" "numpy>=1.21" "gymnasium>=1.0,<2" "pytest>=7" "safetensors>=0.4" "mypy>=1.10")
if [[ ",${PROMPTDT_PY_EXTRAS:-}," == *",minari,"* ]]; then
    pkgs+=("minari[hdf5]>=0.5,<0.6" "pillow")  # minari 0.5.4's hdf5 storage imports PIL
fi
"$venv/bin/python" -m pip install -q --disable-pip-version-check "${pkgs[@]}"

libs=crates/python/python/promptdt/_libs
rm -rf "$libs.tmp"
mkdir -p "$libs.tmp"
for f in third_party/libtorch/torch/lib/libtorch_cpu.so third_party/libtorch/torch/lib/libc10.so \
         third_party/libtorch/torch/lib/libgomp.so.1 \
         third_party/libtorch/nvidia/cu13/lib/libcudart.so.13 \
         third_party/libtorch/nvidia/cu13/lib/libcupti.so.13 \
         third_party/mujoco/lib/libmujoco.so.3.17.0; do
    # Hard links where the file system allows (no 450 MB copy), copies elsewhere.
    ln "$f" "$libs.tmp/" 2>/dev/null || cp "$f" "$libs.tmp/"
done
rm -rf "$libs"
mv "$libs.tmp" "$libs"

# --- licences of what the wheel bundles -------------------------------------------------------------
# The licence texts of this project and of every library copied into _libs, in promptdt/_licenses/
# (installed beside _libs) and, through pyproject.toml's license-files, in the wheel's
# .dist-info/licenses/ (what `pip show` and `unzip -l` list). Sources: the wheels the libraries come
# from (fetch_libtorch.py / fetch_mujoco.py keep their licence files beside third_party/ installs) and,
# for libgomp, the GPL-3.0 text and GCC Runtime Library Exception in crates/python/licenses/libgomp.
lic=crates/python/python/promptdt/_licenses
rm -rf "$lic.tmp"
mkdir -p "$lic.tmp/promptdt" "$lic.tmp/torch" "$lic.tmp/nvidia-cuda-runtime" "$lic.tmp/nvidia-cuda-cupti" \
    "$lic.tmp/libgomp" "$lic.tmp/mujoco"
for pair in LICENSE:promptdt \
            third_party/libtorch/licenses/torch/LICENSE:torch third_party/libtorch/licenses/torch/NOTICE:torch \
            third_party/libtorch/licenses/nvidia-cuda-runtime/License.txt:nvidia-cuda-runtime \
            third_party/libtorch/licenses/nvidia-cuda-cupti/License.txt:nvidia-cuda-cupti \
            crates/python/licenses/libgomp/COPYING3:libgomp crates/python/licenses/libgomp/COPYING.RUNTIME:libgomp \
            crates/python/licenses/libgomp/README:libgomp \
            third_party/mujoco/LICENSE:mujoco third_party/mujoco/LICENSES_THIRD_PARTY.md:mujoco; do
    f=${pair%:*}
    if [ ! -f "$f" ]; then
        echo "install_python: licence file $f is missing (run scripts/fetch_libtorch.py / fetch_mujoco.py)" >&2
        exit 1
    fi
    cp "$f" "$lic.tmp/${pair##*:}/"
done
rm -rf "$lic"
mv "$lic.tmp" "$lic"
# --- end licences -----------------------------------------------------------------------------------

# The trained agents of the MuJoCo families (2.4 MB), so that `promptdt.collect` works from the
# wheel alone (`promptdt.pretrained_dir`); gitignored there, like _libs.
agents=crates/python/python/promptdt/pretrained
rm -rf "$agents.tmp"
cp -r pretrained "$agents.tmp"
rm -rf "$agents"
mv "$agents.tmp" "$agents"

# maturin's own rpath and linker settings are not wanted: the workspace's .cargo/config.toml
# rustflags stay as they are (so the library crates are not rebuilt), and crates/python/build.rs
# adds the $ORIGIN/_libs rpath.
rm -f target/wheels/promptdt-*.whl
"$venv/bin/maturin" build --release --strip --manifest-path crates/python/Cargo.toml \
    --interpreter "$venv/bin/python" --out target/wheels
wheel=$(ls target/wheels/promptdt-*.whl)
"$venv/bin/python" -m pip install -q --disable-pip-version-check --force-reinstall --no-deps "$wheel"
"$venv/bin/python" -c "import promptdt; print('install_python: promptdt', promptdt.__version__, 'in', '$venv')"
echo "install_python: wheel $wheel ($(du -h "$wheel" | cut -f1)), done in $(( $(date +%s) - start )) s"
