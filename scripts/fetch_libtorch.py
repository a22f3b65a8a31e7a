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
  third_party/libtorch/licenses/<distribution>/             <- each wheel's licence files, as its
      .dist-info/licenses/ has them: torch/{LICENSE,NOTICE} (BSD-3-Clause and the third-party
      notices), nvidia-cuda-runtime/License.txt, nvidia-cuda-cupti/License.txt (NVIDIA's licence).
      They travel with what is built on these libraries (scripts/install_python.sh puts them in the
      wheel). An install made before they were kept gets them on the next run (a few kB of reads).

Standard library only; safe to run concurrently (extracts to a temp dir, then renames into place).

  python3 scripts/fetch_libtorch.py                       CPU part (what the build and CI use)
  python3 scripts/fetch_libtorch.py --cuda [--dest DIR]   also the CUDA part, for --device cuda on a GPU
                                                          machine, into third_party/libtorch-cuda/ (or DIR)
  python3 scripts/fetch_libtorch.py --check [--dest DIR]  link check of what is installed (no GPU needed)

--cuda takes, the same way and with the same sha256 checks, libtorch_cuda.so and the DT_NEEDED closure
it has beyond the CPU install (libc10_cuda.so, libtorch_nvshmem.so, cuBLAS, cuDNN, NCCL, ...) from the
torch wheel and from the NVIDIA wheels that the torch wheel's METADATA pins; see install_cuda() below.
It writes a marker (promptdt-install.txt: versions, files, sha256) so that a second run is a no-op,
runs the link check, and prints the LD_LIBRARY_PATH to use.
"""
import base64
import hashlib
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
import zipfile
import zlib

from wheel_files import read_checked, record_hashes, write_file

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

    def __init__(self, url, block_size=BLOCK):
        self.url, self.pos, self.fetched = url, 0, 0
        self.size = int(self._get(0, 0)[1])
        self.block_start, self.block = -1, b""
        self.block_size = block_size
        self.stop = None  # optional end offset for read-ahead (the CUDA path sets it to a member's end)

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
                end = self.size if self.stop is None or self.stop <= self.pos else min(self.stop, self.size)
                self.block = self._get(self.pos, min(self.pos + max(self.block_size, n), end) - 1)[0]
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


# Each wheel's licence files (PEP 639 puts them under .dist-info/licenses/; older wheels keep them
# directly in .dist-info/). They are installed as licenses/<distribution>/<file name>.
LICENSE_RE = re.compile(r"[^/]+\.dist-info/(?:licenses/)?((?:LICEN[CS]E|NOTICE|COPYING)[^/]*)", re.I)
LICENSES_DIR = "licenses"


def licence_members(zf, dist):
    """(zip member, installed path under licenses/) of a wheel's licence files."""
    out = []
    for name in zf.namelist():
        m = LICENSE_RE.fullmatch(name)
        if m:
            out.append((name, os.path.join(LICENSES_DIR, dist, m.group(1))))
    if not out:
        sys.exit(f"fetch_libtorch: {dist}: no licence file in the wheel's .dist-info")
    return out


def extract_checked(zf, hashes, member, path, url):
    write_file(path, read_checked(zf, hashes, member, "fetch_libtorch", url))


def install_licences(dest):
    """Adds licenses/ to an install made before the licence files were kept: only those members
    are read (the zip index and a few kB per wheel), into a temporary directory renamed into place."""
    tmp = tempfile.mkdtemp(prefix=".licenses-", dir=dest)
    try:
        for dist, version, pattern, _ in WHEELS:
            url = wheel_url(dist, pattern)
            zf = zipfile.ZipFile(HttpRangeFile(url, block_size=1 << 20))
            hashes = record_hashes(zf)
            for member, rel in licence_members(zf, dist):
                extract_checked(zf, hashes, member, os.path.join(tmp, rel), url)
        try:
            os.rename(os.path.join(tmp, LICENSES_DIR), os.path.join(dest, LICENSES_DIR))
        except OSError:
            if not os.path.isdir(os.path.join(dest, LICENSES_DIR)):  # not a concurrent run's win
                raise
        print(f"fetch_libtorch: added the wheels' licence files to {dest}/{LICENSES_DIR}", file=sys.stderr)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def install_cpu():
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "third_party")
    dest = os.path.normpath(os.path.join(root, "libtorch"))
    stamp = os.path.join(dest, "torch", "build-version")
    if os.path.exists(stamp) and open(stamp).read().strip() == TORCH_VERSION:
        if not os.path.isdir(os.path.join(dest, LICENSES_DIR)):
            install_licences(dest)
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
                path = os.path.join(tmp, i.filename)
                extract_checked(zf, hashes, i.filename, path, url)
                if ".so" in i.filename:
                    os.chmod(path, 0o755)
            for member, rel in licence_members(zf, dist):
                extract_checked(zf, hashes, member, os.path.join(tmp, rel), url)
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


# ---------------------------------------------------------------------------------------------------
# --cuda: the CUDA part of the same libtorch 2.11.0, for `promptdt ... --device cuda` on a GPU machine.
#
# A promptdt binary links only libtorch_cpu.so (from third_party/libtorch, through its RUNPATH). With
# --device cuda|auto it dlopen()s "libtorch_cuda.so" by name (crates/torch/src/device.rs), which
# registers the CUDA backend with the already-loaded libtorch_cpu.so. So the CUDA install is a separate
# directory with the wheel's layout (torch/lib + nvidia/<pkg>/lib: the torch libraries' DT_RPATH,
# $ORIGIN/../../nvidia/{cudnn,nvshmem,nccl,cusparselt,cu13}/lib, then finds the NVIDIA libraries without
# any environment variable) holding what libtorch_cuda.so needs beyond the CPU install, and only its
# torch/lib goes on LD_LIBRARY_PATH. It must not hold libtorch_cpu.so, libc10.so or libgomp.so.1: those
# are already loaded from the CPU install (same wheel, so the same files) and are matched by SONAME.
#
# What is installed is derived, not listed: the DT_NEEDED closure of CUDA_ROOTS, read with the ELF
# reader below from the extracted files themselves, where each library comes from torch/lib of the
# torch wheel or from the NVIDIA wheel that torch 2.11.0's METADATA pins (Requires-Dist, expanding
# cuda-toolkit[...]==13.0.2 through that wheel's own METADATA). Nothing else of those wheels is taken
# but the libraries that CUDA_DLOPENED names.
# ---------------------------------------------------------------------------------------------------

# libtorch_cuda.so is what device.rs loads; libtorch loads the other two itself with dlopen the first
# time they are used (linear-algebra ops such as torch.linalg.* through cuSOLVER, and NVRTC-compiled
# "jiterator" kernels), so they are installed too rather than failing mid-run.
CUDA_ROOTS = ("libtorch_cuda.so", "libtorch_cuda_linalg.so", "libcaffe2_nvrtc.so")
# Libraries that load companions with dlopen (not DT_NEEDED): when the key is installed, the members
# of the same wheel directory matching the pattern are installed too.
CUDA_DLOPENED = {
    "libcudnn.so.9": r"libcudnn_[a-z_]+\.so\.9",             # cuDNN 9's sub-libraries
    "libnvrtc.so.13": r"libnvrtc-builtins\.so\.13\.0",        # NVRTC's builtins
}
# Come with the NVIDIA driver, never from a wheel; on a machine without one they are absent.
DRIVER_LIBS = ("libcuda.so.1", "libnvidia-ml.so.1")
CUDA_FORMAT = 1
CUDA_MARKER = "promptdt-install.txt"
CUDA_BLOCK = 16 << 20
SYSTEM_DIRS = ("/lib/x86_64-linux-gnu", "/usr/lib/x86_64-linux-gnu", "/lib64", "/usr/lib64", "/lib", "/usr/lib")


def die(msg):
    sys.exit(f"fetch_libtorch: {msg}")


def elf_dynamic(path):
    """SONAME, DT_NEEDED, DT_RPATH and DT_RUNPATH of an x86-64 ELF file; None if it is not ELF.

    Pure Python (no binutils): program headers -> PT_DYNAMIC -> DT_STRTAB, mapped to a file offset
    through the PT_LOAD segment that contains it."""
    with open(path, "rb") as f:
        hdr = f.read(64)
        if len(hdr) < 64 or hdr[:4] != b"\x7fELF":
            return None
        if hdr[4] != 2 or hdr[5] != 1:
            die(f"{path}: not a 64-bit little-endian ELF file")
        (machine,) = struct.unpack_from("<H", hdr, 18)
        if machine != 62:
            die(f"{path}: ELF machine {machine}, not x86-64")
        (phoff,) = struct.unpack_from("<Q", hdr, 32)
        phentsize, phnum = struct.unpack_from("<HH", hdr, 54)
        f.seek(phoff)
        ph = f.read(phentsize * phnum)
        loads, dyn = [], None
        for k in range(phnum):
            p_type, _, p_offset, p_vaddr, _, p_filesz, _, _ = struct.unpack_from("<IIQQQQQQ", ph, k * phentsize)
            if p_type == 1:
                loads.append((p_vaddr, p_offset, p_filesz))
            elif p_type == 2:
                dyn = (p_offset, p_filesz)
        out = {"soname": None, "needed": [], "rpath": [], "runpath": []}
        if dyn is None:
            return out
        f.seek(dyn[0])
        raw = f.read(dyn[1])
        entries = []
        for k in range(0, len(raw) - 15, 16):
            tag, val = struct.unpack_from("<qQ", raw, k)
            if tag == 0:
                break
            entries.append((tag, val))
        tags = dict(entries)
        if 5 not in tags:
            return out
        strtab, strsz = tags[5], tags.get(10, 0)
        for vaddr, off, filesz in loads:
            if vaddr <= strtab < vaddr + filesz:
                f.seek(strtab - vaddr + off)
                strs = f.read(strsz)
                break
        else:
            die(f"{path}: DT_STRTAB is outside every PT_LOAD segment")

    def string(i):
        return strs[i:strs.index(b"\0", i)].decode()

    origin = os.path.dirname(os.path.abspath(path))
    for tag, val in entries:
        if tag == 1:
            out["needed"].append(string(val))
        elif tag == 14:
            out["soname"] = string(val)
        elif tag in (15, 29):
            dirs = [d.replace("$ORIGIN", origin).replace("${ORIGIN}", origin) for d in string(val).split(":") if d]
            out["rpath" if tag == 15 else "runpath"] += [os.path.normpath(d) for d in dirs]
    return out


class Wheel:
    """One remote wheel: its zip index over HTTP ranges, its RECORD, and checked extraction."""

    def __init__(self, dist, version, url):
        self.dist, self.version, self.url = dist, version, url
        self.f = HttpRangeFile(url, block_size=CUDA_BLOCK)
        self.zf = zipfile.ZipFile(self.f)
        self.infos = {i.filename: i for i in self.zf.infolist()}
        self._hashes = None
        starts = sorted(i.header_offset for i in self.zf.infolist()) + [getattr(self.zf, "start_dir", None)]
        self._next = {a: b for a, b in zip(starts, starts[1:])}

    def read_text(self, suffix):
        names = [n for n in self.infos if n.endswith(suffix)]
        if len(names) != 1:
            die(f"{self.url}: expected one *{suffix}, found {names}")
        return self.zf.read(names[0]).decode()

    def extract(self, member, root):
        """Streams one member to root/member, checking it against the RECORD's sha256.

        Returns (size, sha256 in hex)."""
        if self._hashes is None:
            self._hashes = record_hashes(self.zf)
        info = self.infos[member]
        want = self._hashes.get(member)
        if want is None:
            die(f"{member} in {self.url} has no sha256 in the wheel's RECORD")
        path = os.path.join(root, member)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        self.f.stop = self._next.get(info.header_offset)  # read ahead no further than this member
        h, size = hashlib.sha256(), 0
        try:
            with self.zf.open(info) as src, open(path, "wb") as out:
                while True:
                    chunk = src.read(4 << 20)
                    if not chunk:
                        break
                    h.update(chunk)
                    out.write(chunk)
                    size += len(chunk)
        except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            die(f"reading {member} from {self.url}: {e}")
        finally:
            self.f.stop = None
        got = base64.urlsafe_b64encode(h.digest()).rstrip(b"=").decode()
        if got != want:
            die(f"sha256 mismatch for {member} in {self.url}: RECORD says {want}, the download is {got}")
        os.chmod(path, 0o755)
        return size, h.hexdigest()


def parse_requirement(line):
    """'name[extras]==version; marker' -> (name, [extras], version, marker), or None if not pinned with ==."""
    m = re.match(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[([^\]]*)\])?\s*==\s*([0-9][0-9A-Za-z.+*!]*)\s*(?:;(.*))?$",
                 line)
    if not m:
        return None
    extras = [e.strip() for e in (m.group(2) or "").split(",") if e.strip()]
    return m.group(1).lower(), extras, m.group(3), (m.group(4) or "").strip()


def requires_dist(metadata):
    return [l.split(":", 1)[1].strip() for l in metadata.splitlines() if l.startswith("Requires-Dist:")]


def linux_marker(marker, extra=None):
    """True if a marker holds on Linux x86-64 (with `extra` requested; no extra if None)."""
    extras = re.findall(r"extra\s*==\s*['\"]([^'\"]+)['\"]", marker)
    if extras and extra not in extras or not extras and extra is not None:
        return False
    platforms = re.findall(r"(?:platform_system|sys_platform)\s*==\s*['\"]([^'\"]+)['\"]", marker)
    return not platforms or any(p.lower() == "linux" for p in platforms)


def version_key(v):
    return [int(x) if x.isdigit() else -1 for x in re.split(r"[.+!-]|(?<=\d)(?=[a-z])", v)]


def find_wheel(dist, spec):
    """URL and exact version of the x86-64 Linux wheel of `dist` that matches `==spec` (X or X.*)."""
    index = f"https://pypi.org/simple/{dist}/"
    try:
        with urllib.request.urlopen(index, timeout=60) as r:
            html = r.read().decode()
    except OSError as e:
        die(f"{index}: {e}")
    norm = re.sub(r"[-_.]+", "_", dist)
    prefix = spec[:-2] if spec.endswith(".*") else None
    found = []
    for url, name in re.findall(r'href="(https://[^"#]*/([^"#/]+\.whl))#sha256=[0-9a-f]+"', html):
        m = re.match(re.escape(norm) + r"-([^-]+)-(?:[^-]+-)?([^-]+)-[^-]+-([^-]+)\.whl$", name, re.I)
        if not m or not {"py3", "cp311"} & set(m.group(2).split(".")):
            continue
        if m.group(3) != "any" and not ("manylinux" in m.group(3) and "x86_64" in m.group(3)):
            continue
        v = m.group(1)
        if v == (prefix or spec) or prefix and (v.startswith(prefix + ".") or v.startswith(prefix + "post")):
            found.append((version_key(v), name, url, v))
    if not found:
        die(f"no x86-64 manylinux wheel of {dist}=={spec} in {index}")
    exact = [x for x in found if x[3] == (prefix or spec)]
    _, _, url, v = sorted(exact or found)[-1]
    return url, v


def cuda_wheels(torch_wheel):
    """{dist: (version spec, why)} for the NVIDIA wheels torch's METADATA pins on Linux."""
    pins = {}
    for req in requires_dist(torch_wheel.read_text(".dist-info/METADATA")):
        r = parse_requirement(req)
        if not r or not linux_marker(r[3]):
            continue
        name, extras, spec, _ = r
        if name.startswith("nvidia-"):
            pins[name] = (spec, f"torch {TORCH_VERSION}: {req}")
        elif name == "cuda-toolkit":
            url, v = find_wheel(name, spec)
            meta = Wheel(name, v, url).read_text(".dist-info/METADATA")
            for sub in requires_dist(meta):
                s = parse_requirement(sub)
                if s and any(linux_marker(s[3], extra=e) for e in extras):
                    pins.setdefault(s[0], (s[2], f"cuda-toolkit {v}[...]: {sub.split(';')[0].strip()}"))
    if not pins:
        die(f"torch {TORCH_VERSION}'s METADATA pins no NVIDIA wheels for Linux")
    return pins


def lib_files(root):
    """Every ELF shared library (regular file) under root, as absolute paths."""
    out = []
    for d, _, files in os.walk(root):
        for n in sorted(files):
            p = os.path.join(d, n)
            if ".so" in n and os.path.isfile(p) and not os.path.islink(p) and elf_dynamic(p) is not None:
                out.append(p)
    return sorted(out)


def cpu_sonames(cpu_dest):
    """SONAME -> path of the libraries of the CPU install: all loaded by promptdt before libtorch_cuda."""
    out = {}
    for p in lib_files(cpu_dest):
        info = elf_dynamic(p)
        out[info["soname"] or os.path.basename(p)] = p
    return out


def read_marker(dest):
    path = os.path.join(dest, CUDA_MARKER)
    try:
        with open(path) as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    return lines


def marker_header():
    return f"promptdt libtorch-cuda {TORCH_VERSION} format {CUDA_FORMAT} roots {','.join(CUDA_ROOTS)}"


def marker_ok(dest):
    """True if dest holds a complete install of this version/set (marker present, every file with its size)."""
    lines = read_marker(dest)
    if not lines or lines[0] != marker_header():
        return False
    for line in lines[1:]:
        parts = line.split()
        if parts and parts[0] == "file":
            p = os.path.join(dest, parts[1])
            if not os.path.isfile(p) or os.path.getsize(p) != int(parts[2]):
                return False
    return True


def install_cuda(dest, cpu_dest):
    """Installs the CUDA part into dest (idempotent); returns True if it downloaded anything."""
    if marker_ok(dest):
        files = [l.split() for l in read_marker(dest) if l.startswith("file ")]
        size = sum(int(p[2]) for p in files)
        print(f"fetch_libtorch: libtorch {TORCH_VERSION} CUDA part already installed in {dest} "
              f"({len(files)} libraries, {size / 1e6:.0f} MB; marker {CUDA_MARKER}): nothing to do", file=sys.stderr)
        return False
    preloaded = cpu_sonames(cpu_dest)
    parent = os.path.dirname(dest)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix="." + os.path.basename(dest) + "-", dir=parent)
    t0 = time.time()
    try:
        torch = Wheel("torch", TORCH_VERSION, wheel_url("torch", WHEELS[0][2]))
        pins = cuda_wheels(torch)
        # Check that the CPU install's NVIDIA runtime wheels are the versions this torch pins.
        for dist, version, _, _ in WHEELS[1:]:
            spec = pins.get(dist, (version,))[0]
            if not (version == spec or spec.endswith(".*") and (version + ".").startswith(spec[:-1])):
                print(f"fetch_libtorch: warning: the CPU install has {dist} {version}, torch pins {spec}",
                      file=sys.stderr)
        # Who provides each library file name: torch/lib of the torch wheel, nvidia/*/lib of the pins.
        wheels = {"torch": torch}
        providers = {}
        for n in torch.infos:
            if re.fullmatch(r"torch/lib/[^/]+\.so(\.[0-9]+)*", n):
                providers[os.path.basename(n)] = ("torch", n)
        for dist, (spec, why) in sorted(pins.items()):
            url, v = find_wheel(dist, spec)
            w = wheels[dist] = Wheel(dist, v, url)
            w.why = why
            for n in w.infos:
                if re.fullmatch(r"nvidia/[^/]+/lib/[^/]+\.so(\.[0-9]+)*", n):
                    providers.setdefault(os.path.basename(n), (dist, n))
        # Walk the DT_NEEDED closure from the roots, extracting (and checking) each library as we go.
        todo, done, system = list(CUDA_ROOTS), {}, set()
        while todo:
            name = todo.pop(0)
            if name in done or name in preloaded or name in system:
                continue
            if name not in providers:
                if name in CUDA_ROOTS:
                    die(f"torch/lib/{name} is not in {torch.url}")
                system.add(name)  # libc, libstdc++, libcuda.so.1 ...: checked by the link check
                continue
            dist, member = providers[name]
            w = wheels[dist]
            t1, f0 = time.time(), w.f.fetched
            size, digest = w.extract(member, tmp)
            done[name] = (dist, w.version, member, size, digest)
            print(f"fetch_libtorch:   {member} ({dist} {w.version}): {size / 1e6:.1f} MB, "
                  f"{(w.f.fetched - f0) / 1e6:.1f} MB downloaded in {time.time() - t1:.0f} s", file=sys.stderr)
            todo += elf_dynamic(os.path.join(tmp, member))["needed"]
            if name in CUDA_DLOPENED:
                d = os.path.dirname(member)
                todo += sorted(os.path.basename(n) for n in w.infos if os.path.dirname(n) == d
                               and re.fullmatch(CUDA_DLOPENED[name], os.path.basename(n)))
        total = sum(w.f.fetched for w in wheels.values())
        used = sorted({(d, v) for d, v, _, _, _ in done.values()})
        lines = [marker_header()]
        for dist, v in used:
            lines.append(f"wheel {dist} {v} {wheels[dist].url} ({getattr(wheels[dist], 'why', 'the torch wheel')})")
        for dist, v, member, size, digest in sorted(done.values(), key=lambda x: x[2]):
            lines.append(f"file {member} {size} sha256={digest} {dist}=={v}")
        with open(os.path.join(tmp, CUDA_MARKER), "w") as out:
            out.write("\n".join(lines) + "\n")
        os.chmod(tmp, 0o755)  # mkdtemp made it 0700
        if marker_ok(dest):  # a concurrent run finished first: keep its install
            print(f"fetch_libtorch: a concurrent run installed {dest} first; keeping it", file=sys.stderr)
            return True
        old = None
        if os.path.exists(dest):  # a stale or partial install: move it aside, then remove it
            old = tempfile.mkdtemp(prefix="." + os.path.basename(dest) + "-old-", dir=parent)
            os.rename(dest, os.path.join(old, "x"))
        try:
            os.rename(tmp, dest)
        except OSError:
            if not marker_ok(dest):  # lost a race to a concurrent run that did not finish
                raise
        if old:
            shutil.rmtree(old, ignore_errors=True)
        size = sum(x[3] for x in done.values())
        print(f"fetch_libtorch: installed the CUDA part of libtorch {TORCH_VERSION} in {dest}: "
              f"{len(done)} libraries from {len(used)} wheels ({', '.join(f'{d} {v}' for d, v in used)}), "
              f"{size / 1e6:.0f} MB on disk; downloaded {total / 1e6:.0f} MB in {time.time() - t0:.0f} s",
              file=sys.stderr)
        return True
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def system_libs():
    """SONAME -> path for the x86-64 libraries in the dynamic loader's cache (ldconfig -p)."""
    out = {}
    for ldconfig in ("/sbin/ldconfig", "/usr/sbin/ldconfig", "ldconfig"):
        try:
            text = subprocess.run([ldconfig, "-p"], capture_output=True, text=True, check=True).stdout
        except (OSError, subprocess.CalledProcessError):
            continue
        for m in re.finditer(r"^\s*(\S+) \(([^)]*)\) => (\S+)$", text, re.M):
            if "x86-64" in m.group(2):
                out.setdefault(m.group(1), m.group(3))
        break
    return out


def link_check(cpu_dest, cuda_dest, ld_library_path):
    """Checks, without a GPU, that every DT_NEEDED of every installed library resolves.

    Resolution follows the dynamic loader as promptdt meets it: the CPU install is loaded first (the
    binary's RUNPATH), so its SONAMEs are taken as loaded for the CUDA libraries; then the library's
    own DT_RPATH (if it has no DT_RUNPATH) and those of the libraries that need it; LD_LIBRARY_PATH;
    its DT_RUNPATH; the loader cache and the default directories. Returns the number of problems."""
    cache = system_libs()
    objs = {}
    for label, root in (("cpu", cpu_dest), ("cuda", cuda_dest)):
        if root and os.path.isdir(root):
            for p in lib_files(root):
                objs[p] = (label, elf_dynamic(p))
    cpu_loaded = {(i["soname"] or os.path.basename(p)): p for p, (label, i) in objs.items() if label == "cpu"}
    parents = {}
    for p, (_, info) in objs.items():
        for n in info["needed"]:
            parents.setdefault(n, []).append(p)
    problems, notes, counts = [], set(), {"install": 0, "loaded": 0, "system": 0}

    def find(name, dirs):
        for d in dirs:
            p = os.path.join(d, name)
            if os.path.isfile(p) and elf_dynamic(p) is not None:
                return p
        return None

    for p, (label, info) in sorted(objs.items()):
        for name in info["needed"]:
            if label == "cuda" and name in cpu_loaded:
                counts["loaded"] += 1
                continue
            dirs = []
            if not info["runpath"]:
                dirs += info["rpath"]
                for q in parents.get(info["soname"] or os.path.basename(p), []):
                    if not objs[q][1]["runpath"]:
                        dirs += objs[q][1]["rpath"]
            dirs += ld_library_path + info["runpath"]
            hit = find(name, dirs)
            if hit:
                counts["install" if any(hit.startswith(r + os.sep) for r in (cpu_dest, cuda_dest) if r)
                       else "system"] += 1
                continue
            if name in cache or find(name, SYSTEM_DIRS):
                counts["system"] += 1
            elif name in DRIVER_LIBS:
                notes.add(name)
            else:
                problems.append(f"{p}: DT_NEEDED {name} resolves nowhere")
    # The names loaded with dlopen: device.rs loads libtorch_cuda.so, and libtorch (from libtorch_cpu.so,
    # whose own DT_RPATH does not see the CUDA install) loads the other roots, all through LD_LIBRARY_PATH.
    if cuda_dest and os.path.isdir(cuda_dest):
        for name in CUDA_ROOTS:
            if not find(name, ld_library_path):
                problems.append(f"dlopen(\"{name}\"): not found on LD_LIBRARY_PATH {':'.join(ld_library_path)}")
        for key, pattern in CUDA_DLOPENED.items():
            for p in objs:
                if os.path.basename(p) == key and not any(
                        re.fullmatch(pattern, n) for n in os.listdir(os.path.dirname(p))):
                    problems.append(f"{p} loads {pattern} with dlopen, but none is next to it")
        # LD_LIBRARY_PATH comes before the binary's RUNPATH: it must not shadow the CPU install.
        for soname in cpu_loaded:
            hit = find(soname, ld_library_path)
            if hit:
                problems.append(f"{hit} on LD_LIBRARY_PATH would shadow the CPU install's {soname}")
    n = sum(len(i["needed"]) for _, i in objs.values())
    print(f"fetch_libtorch: link check: {len(objs)} libraries, {n} DT_NEEDED entries: {counts['install']} found "
          f"in the install directories, {counts['loaded']} already loaded from the CPU install, "
          f"{counts['system']} system libraries", file=sys.stderr)
    for name in sorted(notes):
        print(f"fetch_libtorch: link check: {name} is not on this machine; it comes with the NVIDIA driver",
              file=sys.stderr)
    for msg in problems:
        print(f"fetch_libtorch: link check: ERROR: {msg}", file=sys.stderr)
    print(f"fetch_libtorch: link check: {'OK' if not problems else f'{len(problems)} problem(s)'}", file=sys.stderr)
    return len(problems)


LOAD_TEST = r"""
import ctypes, json, os, sys
cpu, libs = sys.argv[1], json.loads(sys.argv[2])
ctypes.CDLL(cpu, mode=os.RTLD_NOW | os.RTLD_GLOBAL)
out = {}
for lib in libs:
    try:
        ctypes.CDLL(lib, mode=os.RTLD_NOW | os.RTLD_GLOBAL)
        out[lib] = None
    except OSError as e:
        out[lib] = str(e)
print(json.dumps(out))
"""


def load_test(cpu_dest, cuda_dest, ld_library_path):
    """dlopen()s the CUDA install's libraries (RTLD_NOW, as device.rs does) in a child process that has
    first loaded the CPU install's libtorch_cpu.so, with the LD_LIBRARY_PATH to be printed: every symbol
    must bind. No GPU is needed for that; libraries that need an NVIDIA driver library absent here
    (libcuda.so.1) cannot be loaded and are named instead. Returns the number of failures."""
    objs = {p: elf_dynamic(p) for p in lib_files(cuda_dest)}
    by_name = {(i["soname"] or os.path.basename(p)): p for p, i in objs.items()}
    have = set(by_name) | set(cpu_sonames(cpu_dest)) | set(system_libs())

    def missing(p, seen):
        out = set()
        for n in objs[p]["needed"]:
            if n in by_name and n not in seen:
                seen.add(n)
                out |= missing(by_name[n], seen)
            elif n not in have and not any(os.path.isfile(os.path.join(d, n)) for d in SYSTEM_DIRS):
                out.add(n)
        return out

    roots = [by_name[n] for n in CUDA_ROOTS if n in by_name]
    testable, skipped = [], {}
    for p in roots + sorted(p for p in objs if p not in roots):
        m = missing(p, set())
        if m:
            skipped[p] = m
        else:
            testable.append(p)
    env = dict(os.environ, LD_LIBRARY_PATH=":".join(ld_library_path + [os.environ.get("LD_LIBRARY_PATH", "")]).rstrip(":"))
    t0 = time.time()
    r = subprocess.run([sys.executable, "-c", LOAD_TEST, os.path.join(cpu_dest, "torch", "lib", "libtorch_cpu.so"),
                        json.dumps(testable)], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        print(f"fetch_libtorch: load test: ERROR: the child process failed ({r.returncode}): {r.stderr.strip()[-2000:]}",
              file=sys.stderr)
        return 1
    res = json.loads(r.stdout)
    bad = {p: e for p, e in res.items() if e}
    print(f"fetch_libtorch: load test: dlopen(RTLD_NOW) of {len(res) - len(bad)} of {len(res)} libraries OK "
          f"({time.time() - t0:.1f} s)", file=sys.stderr)
    for p, m in skipped.items():
        print(f"fetch_libtorch: load test: {os.path.relpath(p, cuda_dest)} not loaded here: needs "
              f"{', '.join(sorted(m))}, absent on this machine", file=sys.stderr)
    for p, e in bad.items():
        print(f"fetch_libtorch: load test: ERROR: {p}: {e}", file=sys.stderr)
    return len(bad)


def main():
    import argparse
    ap = argparse.ArgumentParser(description="Install libtorch 2.11.0 (CPU part; with --cuda also the CUDA part).")
    ap.add_argument("--cuda", action="store_true",
                    help="also install the CUDA part (libtorch_cuda.so and the NVIDIA libraries it needs) into DEST")
    ap.add_argument("--dest", help="where the CUDA part goes (default third_party/libtorch-cuda)")
    ap.add_argument("--check", action="store_true",
                    help="link check only: every DT_NEEDED of the installed libraries resolves (no GPU needed)")
    args = ap.parse_args()
    if not args.cuda and not args.check:
        if args.dest:
            ap.error("--dest goes with --cuda or --check")
        return install_cpu()
    third_party = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "third_party"))
    cpu_dest = os.path.join(third_party, "libtorch")
    dest = os.path.abspath(args.dest) if args.dest else os.path.join(third_party, "libtorch-cuda")
    if args.cuda:
        install_cpu()  # libtorch_cuda.so needs the CPU part (a no-op when it is there)
        install_cuda(dest, cpu_dest)
    elif not os.path.isdir(cpu_dest):
        die(f"no CPU install at {cpu_dest} (run scripts/fetch_libtorch.py)")
    cuda = dest if os.path.isdir(dest) else None
    if args.check and cuda and not marker_ok(dest):
        print(f"fetch_libtorch: warning: {dest} has no complete install marker ({CUDA_MARKER})", file=sys.stderr)
    lib = os.path.join(dest, "torch", "lib")
    bad = link_check(cpu_dest, cuda, [lib] if cuda else [])
    if cuda and not bad:
        bad += load_test(cpu_dest, cuda, [lib])
    if cuda:
        print(f"fetch_libtorch: to use it: LD_LIBRARY_PATH={lib}${{LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}} "
              f"promptdt ... --device cuda", file=sys.stderr)
        print(f"LD_LIBRARY_PATH={lib}")
    if bad:
        sys.exit(1)


if __name__ == "__main__":
    main()
