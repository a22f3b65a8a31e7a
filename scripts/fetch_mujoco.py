#!/usr/bin/env python3
"""Install the MuJoCo 3.17.0 shared library and C headers into third_party/mujoco/, idempotently.

Why this script: the Rust crate mujoco-rs (=7.0.0) binds MuJoCo 3.17.0 but does not build it, and
MuJoCo's own CMake build downloads its dependencies from GitHub. The PyPI wheel `mujoco==3.17.0`
carries the same self-contained `libmujoco.so.3.17.0` that the Python bindings load (needs only
libc/libm/libdl/libpthread/librt, glibc >= 2.27, an AVX CPU) and the C headers. Every CPython
version's manylinux x86_64 wheel holds the same library, so any of them will do; cp311 is preferred
because its sha256 is pinned below. The wheel (~26 MB) is downloaded whole, checked against the
index's sha256, and each extracted file is checked against the wheel's RECORD; the library is also
checked against a pinned sha256.

Layout (what pkgconfig/mujoco.pc points at; crates/envs/build.rs runs this script when it is missing):
  third_party/mujoco/lib/libmujoco.so.3.17.0    the library (SONAME libmujoco.so.3.17.0)
  third_party/mujoco/lib/libmujoco.so           symlink to it (the wheel has no unversioned name)
  third_party/mujoco/include/mujoco/*.h         the C API headers
  third_party/mujoco/LICENSE, LICENSES_THIRD_PARTY.md
  third_party/mujoco/build-version              "3.17.0" once the install is complete

Standard library only; safe to run concurrently (extracts to a temp dir, then renames into place).
"""
import hashlib
import os
import re
import sys
import time
import zipfile

from wheel_files import download_checked, http_get, install_atomically, read_checked, record_hashes, write_file

MUJOCO_VERSION = "3.17.0"
INDEX = "https://pypi.org/simple/mujoco/"
# Any CPython manylinux x86_64 wheel of this version (they differ only in the Python extensions).
WHEEL_RE = r"mujoco-3\.17\.0-(cp3\d+)-cp3\d+t?-manylinux[^\"#]*x86_64[^\"#]*\.whl"
PREFERRED_WHEEL = "mujoco-3.17.0-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl"
PREFERRED_WHEEL_SHA256 = "d66928d86a2d1b601bbaa4dc11db50214d17d5301bb8afd84721313b67ff0874"
LIB_NAME = "libmujoco.so.3.17.0"
LIB_SHA256 = "23496b023ee80fb61ab71167e94bc649f9941710fde96b18bb8204fb332523ad"


def log(msg):
    print(f"fetch_mujoco: {msg}", file=sys.stderr)


def find_wheel():
    """Returns (file name, url, sha256) of the wheel to use, from PyPI's simple index."""
    html = http_get(INDEX, "fetch_mujoco", timeout=60).decode()
    found = {}
    for m in re.finditer(r'href="(https://[^"#]*/(' + WHEEL_RE + r'))#sha256=([0-9a-f]{64})"', html):
        found[m.group(2)] = (m.group(1), m.group(4))
    if not found:
        sys.exit(f"fetch_mujoco: no manylinux x86_64 wheel of mujoco {MUJOCO_VERSION} in {INDEX}")
    name = PREFERRED_WHEEL if PREFERRED_WHEEL in found else sorted(found)[0]
    url, sha = found[name]
    if name == PREFERRED_WHEEL and sha != PREFERRED_WHEEL_SHA256:
        sys.exit(f"fetch_mujoco: the index lists sha256 {sha} for {name}, expected {PREFERRED_WHEEL_SHA256}")
    return name, url, sha


def destination(member):
    """Where a wheel member goes inside third_party/mujoco, or None to skip it."""
    if member == "mujoco/" + LIB_NAME:
        return os.path.join("lib", LIB_NAME)
    m = re.fullmatch(r"mujoco/include/mujoco/([^/]+\.h)", member)
    if m:  # the C API only; the experimental/ and render/ C++ headers are not needed
        return os.path.join("include", "mujoco", m.group(1))
    m = re.fullmatch(r"mujoco-[^/]+\.dist-info/licenses/(LICENSE|LICENSES_THIRD_PARTY\.md)", member)
    if m:
        return m.group(1)
    return None


def populate(tmp):
    """Downloads the wheel and extracts the checked library, headers and licences into `tmp`."""
    name, url, sha = find_wheel()
    log(f"downloading {name}")
    wheel_path = os.path.join(tmp, name)
    size = download_checked(url, sha, wheel_path, "fetch_mujoco")
    with zipfile.ZipFile(wheel_path) as zf:
        hashes = record_hashes(zf)
        wanted = [(i, destination(i.filename)) for i in zf.infolist()]
        wanted = [(i, d) for i, d in wanted if d is not None]
        if not any(d.endswith(LIB_NAME) for _, d in wanted):
            sys.exit(f"fetch_mujoco: {name} has no mujoco/{LIB_NAME}")
        for info, rel in wanted:
            blob = read_checked(zf, hashes, info.filename, "fetch_mujoco", url)
            if rel.endswith(LIB_NAME) and hashlib.sha256(blob).hexdigest() != LIB_SHA256:
                sys.exit(f"fetch_mujoco: {LIB_NAME} in {name} is not the pinned build (sha256)")
            path = os.path.join(tmp, rel)
            write_file(path, blob)
            if rel.endswith(LIB_NAME):
                os.chmod(path, 0o755)
    os.remove(wheel_path)
    # The linker looks for libmujoco.so (-lmujoco); the loader then wants the SONAME.
    os.symlink(LIB_NAME, os.path.join(tmp, "lib", "libmujoco.so"))
    return size


def main():
    root = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "third_party"))
    t0 = time.time()
    size = install_atomically(root, "mujoco", MUJOCO_VERSION, populate)
    if size is not None:
        log(f"installed MuJoCo {MUJOCO_VERSION} in {os.path.join(root, 'mujoco')} "
            f"({size / 1e6:.0f} MB wheel, {time.time() - t0:.1f} s)")


if __name__ == "__main__":
    main()
