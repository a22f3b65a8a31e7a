#!/usr/bin/env python3
"""Install the CPU part of libtorch 2.11.0 into third_party/libtorch/, idempotently.

Why this script and not `pip install torch`: the PyPI wheel is 530 MB and its default dependencies add
~3 GB of CUDA wheels, but a CPU build of tch links only libtorch_cpu.so, libc10.so and libgomp, plus
the headers that torch-sys compiles its C++ wrapper against. The wheel is a zip file, and PyPI's file
host answers HTTP range requests, so we read the zip's central directory remotely and download only
those members (~135 MB). libtorch_cpu.so lists libcudart.so.13 and libcupti.so.13 as NEEDED (found via
its RPATH $ORIGIN/../../nvidia/cu13/lib), so the same is done for the two small NVIDIA runtime wheels.
Every extracted file is checked against the sha256 in its wheel's RECORD.

Layout (what torch-sys wants in LIBTORCH: include/ and lib/):
  third_party/libtorch/torch/{include,lib,build-version}   <- LIBTORCH (set in .cargo/config.toml)
  third_party/libtorch/nvidia/cu13/lib/                     <- libcudart.so.13, libcupti.so.13

Standard library only; safe to run concurrently (extracts to a temp dir, then renames into place).
"""
import base64
import hashlib
import os
import re
import shutil
import sys
import tempfile
import time
import urllib.request
import zipfile

TORCH_VERSION = "2.11.0"
# (distribution, version, wheel-name regex, member filter, destination prefix mapping)
WHEELS = [
    ("torch", TORCH_VERSION, r"torch-2\.11\.0-cp311-cp311-manylinux_2_28_x86_64\.whl",
     lambda n: n in ("torch/lib/libtorch_cpu.so", "torch/lib/libc10.so", "torch/lib/libgomp.so.1")
     or (n.startswith("torch/include/") and not n.endswith("/"))),
    ("nvidia-cuda-runtime", "13.0.96", r"nvidia_cuda_runtime-13\.0\.96-py3-none-manylinux2014_x86_64[^\"#]*\.whl",
     lambda n: n.startswith("nvidia/cu13/lib/libcudart.so")),
    ("nvidia-cuda-cupti", "13.0.85", r"nvidia_cuda_cupti-13\.0\.85-py3-none-manylinux_2_25_x86_64\.whl",
     lambda n: n.startswith("nvidia/cu13/lib/libcupti.so")),
]
BLOCK = 8 << 20  # bytes per HTTP range request


class HttpRangeFile:
    """A read-only, seekable file over HTTP range requests, with one cached block."""

    def __init__(self, url):
        self.url, self.pos, self.fetched = url, 0, 0
        self.size = int(self._get(0, 0)[1])
        self.block_start, self.block = -1, b""

    def _get(self, start, end):
        for attempt in range(5):
            try:
                req = urllib.request.Request(self.url, headers={"Range": f"bytes={start}-{end}"})
                with urllib.request.urlopen(req, timeout=120) as r:
                    if r.status != 206:
                        raise OSError(f"{self.url}: server ignored the range request (HTTP {r.status})")
                    data = r.read()
                    total = r.headers["Content-Range"].rsplit("/", 1)[1]
                    self.fetched += len(data)
                    return data, total
            except OSError as e:
                if attempt == 4:
                    raise
                print(f"  retrying after: {e}", file=sys.stderr)
                time.sleep(2 ** attempt)


    def seekable(self):
        return True

    def tell(self):
        return self.pos

    def seek(self, off, whence=0):
        self.pos = {0: off, 1: self.pos + off, 2: self.size + off}[whence]
        return self.pos

    def read(self, n=-1):
        if n is None or n < 0:
            n = self.size - self.pos
        out = bytearray()
        while n > 0 and self.pos < self.size:
            if not (self.block_start <= self.pos < self.block_start + len(self.block)):
                self.block_start = self.pos
                self.block = self._get(self.pos, min(self.pos + max(BLOCK, n), self.size) - 1)[0]
            i = self.pos - self.block_start
            chunk = self.block[i:i + n]
            out += chunk
            self.pos += len(chunk)
            n -= len(chunk)
        return bytes(out)


def wheel_url(dist, pattern):
    index = f"https://pypi.org/simple/{dist}/"
    with urllib.request.urlopen(index, timeout=60) as r:
        html = r.read().decode()
    m = re.search(r'href="(https://[^"#]*/(' + pattern + r'))#sha256=[0-9a-f]+"', html)
    if not m:
        sys.exit(f"fetch_libtorch: no wheel matching {pattern} in {index}")
    return m.group(1)


def record_hashes(zf):
    rec = [n for n in zf.namelist() if n.endswith(".dist-info/RECORD")][0]
    hashes = {}
    for line in zf.read(rec).decode().splitlines():
        parts = line.rsplit(",", 2)
        if len(parts) == 3 and parts[1].startswith("sha256="):
            hashes[parts[0]] = parts[1][len("sha256="):]
    return hashes


def main():
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "third_party")
    dest = os.path.normpath(os.path.join(root, "libtorch"))
    stamp = os.path.join(dest, "torch", "build-version")
    if os.path.exists(stamp) and open(stamp).read().strip() == TORCH_VERSION:
        return  # already installed
    os.makedirs(root, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".libtorch-", dir=root)
    t0, total = time.time(), 0
    try:
        for dist, version, pattern, keep in WHEELS:
            url = wheel_url(dist, pattern)
            f = HttpRangeFile(url)
            zf = zipfile.ZipFile(f)
            hashes = record_hashes(zf)
            members = [i for i in zf.infolist() if keep(i.filename)]
            size = sum(i.compress_size for i in members) / 1e6
            print(f"fetch_libtorch: {dist} {version}: {len(members)} files, {size:.0f} MB of "
                  f"{f.size / 1e6:.0f} MB", file=sys.stderr)
            for i in members:
                data = zf.read(i)
                digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
                if hashes.get(i.filename) != digest:
                    sys.exit(f"fetch_libtorch: sha256 mismatch for {i.filename} in {url}")
                path = os.path.join(tmp, i.filename)
                os.makedirs(os.path.dirname(path), exist_ok=True)
                with open(path, "wb") as out:
                    out.write(data)
                if ".so" in i.filename:
                    os.chmod(path, 0o755)
            total += f.fetched
        lib = os.path.join(tmp, "torch", "lib")
        # torch-sys links -ltorch; the wheel's libtorch.so would pull in libtorch_cuda.so (~1 GB of
        # CUDA). A GNU ld linker script in its place forwards to libtorch_cpu.so for CPU builds.
        with open(os.path.join(lib, "libtorch.so"), "w") as out:
            out.write("/* promptdt: CPU-only link shim, see scripts/fetch_libtorch.py */\nINPUT(-ltorch_cpu)\n")
        with open(os.path.join(tmp, "torch", "build-version"), "w") as out:
            out.write(TORCH_VERSION + "\n")
        if os.path.exists(dest):
            shutil.rmtree(dest)
        try:
            os.rename(tmp, dest)
        except OSError:
            if not os.path.exists(stamp):  # lost a race to a concurrent run that did not finish
                raise
        print(f"fetch_libtorch: installed libtorch {TORCH_VERSION} (CPU) in {dest}: downloaded "
              f"{total / 1e6:.0f} MB in {time.time() - t0:.0f} s", file=sys.stderr)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
