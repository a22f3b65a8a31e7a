#!/usr/bin/env bash
# Installs what headless rendering needs (docs/rendering.md): Mesa's EGL, its DRI drivers (the
# llvmpipe software rasteriser where there is no GPU) and GBM, from Debian/Ubuntu packages.
#
#   bash scripts/setup_render.sh          (as root, or with sudo available)
#
# Idempotent: does nothing when the libraries are already there. Nothing else of promptdt needs
# them: binaries and the wheel load libEGL only when asked to render (dlopen), and say which
# packages are missing if they are.
set -euo pipefail
packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1)

present() {
    # The EGL loader, Mesa's EGL vendor library, GBM and a DRI driver (swrast/llvmpipe). The cache
    # is read once (grep -q on a pipe could end ldconfig early, a failure under pipefail).
    local cache
    cache=$(ldconfig -p 2>/dev/null || true)
    grep -q 'libEGL\.so\.1 ' <<<"$cache" &&
        grep -q 'libEGL_mesa\.so\.0 ' <<<"$cache" &&
        grep -q 'libgbm\.so\.1 ' <<<"$cache" &&
        compgen -G '/usr/lib/*/dri/swrast_dri.so' >/dev/null
}

if present; then
    echo "setup_render: EGL and Mesa are installed"
    exit 0
fi
if ! command -v apt-get >/dev/null; then
    echo "setup_render: no apt-get here; install the equivalents of: ${packages[*]}" >&2
    exit 1
fi
sudo=()
if [ "$(id -u)" != 0 ]; then
    if ! command -v sudo >/dev/null; then
        echo "setup_render: run as root (or install sudo) to apt-get install ${packages[*]}" >&2
        exit 1
    fi
    sudo=(sudo)
fi
echo "setup_render: installing ${packages[*]}"
"${sudo[@]}" apt-get update -qq
DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y -qq --no-install-recommends \
    "${packages[@]}"
if ! present; then
    echo "setup_render: the packages are installed but EGL/Mesa libraries were not found" >&2
    exit 1
fi
