#!/usr/bin/env python3
"""Install the Meta-World 3.1.1 Sawyer reach scene (23 asset files + MIT licence) into
third_party/metaworld/, idempotently.

Why this script: the `metaworld_reach` environment of pdt-envs loads Meta-World's own MJCF scene
(sawyer_reach_v3.xml and what it includes: the Sawyer arm, the table, the meshes and textures),
which the project does not vendor. The PyPI wheel `metaworld==3.1.1` (MIT, "Copyright (c) 2019
Meta-World Team") ships the assets; its 275 .py/.xml files are blob-identical to git tag v3.1.1
(7ea2b501c4a698c8533cdc55a396fe2734e2649d). The wheel (~37 MB) is downloaded whole, checked against
the pinned sha256, and each extracted file is checked against the wheel's RECORD; only the 23 files
the reach scene needs (5.3 MB) and the licence are kept. crates/envs/build.rs runs this script when
the install is missing, and embeds the files in the library (include_bytes!), so binaries built
from the crate do not need third_party/ at run time.

Layout (paths under assets/ are those of metaworld/assets/ in the wheel; the scene's includes are
relative, `../scene/basic_scene.xml`, so the tree is kept as is):
  third_party/metaworld/assets/sawyer_xyz/sawyer_reach_v3.xml   the top-level scene
  third_party/metaworld/assets/{scene,objects,textures}/...     what it includes
  third_party/metaworld/LICENSE                                 Meta-World's MIT licence
  third_party/metaworld/build-version                           "3.1.1" once the install is complete

Standard library only; safe to run concurrently (extracts to a temp dir, then renames into place).
"""
import base64
import hashlib
import os
import shutil
import sys
import tempfile
import time
import urllib.request
import zipfile

METAWORLD_VERSION = "3.1.1"
WHEEL = "metaworld-3.1.1-py3-none-any.whl"
WHEEL_URL = (
    "https://files.pythonhosted.org/packages/81/50/3acdb0af5609278e58c388cbc05352da4d046f3df487f5bcca5260eefa44/"
    + WHEEL
)
WHEEL_SHA256 = "99e25d9baf97f2f1a19ca89c0d2ca9c6a2b396d9a9be81729de64eedc683f0d3"
LICENSE_MEMBER = "metaworld-3.1.1.dist-info/licenses/LICENSE"

# The files sawyer_reach_v3.xml needs, relative to metaworld/assets/ (checked: these alone compile).
ASSET_FILES = [
    "sawyer_xyz/sawyer_reach_v3.xml",
    "scene/basic_scene.xml",
    "objects/assets/block_dependencies.xml",
    "objects/assets/xyz_base_dependencies.xml",
    "objects/assets/xyz_base.xml",
    "objects/meshes/table/tablebody.stl",
    "objects/meshes/table/tabletop.stl",
    "objects/meshes/block/block.stl",
] + [
    f"objects/meshes/xyz_base/{name}.stl"
    for name in ("base", "eGripperBase", "head", "l0", "l1", "l2", "l3", "l4", "l5", "l6", "pedestal")
] + [f"textures/{name}.png" for name in ("wood2", "floor2", "metal", "wood4")]


def log(msg):
    print(f"fetch_metaworld: {msg}", file=sys.stderr)


def http_get(url, timeout=300):
    for attempt in range(5):
        try:
            with urllib.request.urlopen(url, timeout=timeout) as r:
                return r.read()
        except OSError as e:
            if attempt == 4:
                raise
            log(f"retrying {url} after: {e}")
            time.sleep(2 ** attempt)


def record_hashes(zf):
    rec = [n for n in zf.namelist() if n.endswith(".dist-info/RECORD")][0]
    hashes = {}
    for line in zf.read(rec).decode().splitlines():
        parts = line.rsplit(",", 2)
        if len(parts) == 3 and parts[1].startswith("sha256="):
            hashes[parts[0]] = parts[1][len("sha256="):]
    return hashes


def main():
    root = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "third_party"))
    dest = os.path.join(root, "metaworld")
    stamp = os.path.join(dest, "build-version")
    if os.path.exists(stamp) and open(stamp).read().strip() == METAWORLD_VERSION:
        return  # already installed
    os.makedirs(root, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".metaworld-", dir=root)
    t0 = time.time()
    try:
        log(f"downloading {WHEEL}")
        data = http_get(WHEEL_URL)
        if hashlib.sha256(data).hexdigest() != WHEEL_SHA256:
            sys.exit(f"fetch_metaworld: sha256 mismatch for {WHEEL_URL}")
        wheel_path = os.path.join(tmp, WHEEL)
        with open(wheel_path, "wb") as out:
            out.write(data)
        with zipfile.ZipFile(wheel_path) as zf:
            hashes = record_hashes(zf)
            members = [("metaworld/assets/" + f, os.path.join("assets", f)) for f in ASSET_FILES]
            members.append((LICENSE_MEMBER, "LICENSE"))
            for member, rel in members:
                blob = zf.read(member)
                digest = base64.urlsafe_b64encode(hashlib.sha256(blob).digest()).rstrip(b"=").decode()
                if hashes.get(member) != digest:
                    sys.exit(f"fetch_metaworld: sha256 mismatch for {member} in {WHEEL}")
                path = os.path.join(tmp, rel)
                os.makedirs(os.path.dirname(path), exist_ok=True)
                with open(path, "wb") as out:
                    out.write(blob)
        os.remove(wheel_path)
        with open(os.path.join(tmp, "build-version"), "w") as out:
            out.write(METAWORLD_VERSION + "\n")
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the install is an ordinary folder
        if os.path.exists(dest):
            shutil.rmtree(dest)
        try:
            os.rename(tmp, dest)
        except OSError:
            if not os.path.exists(stamp):  # lost a race to a concurrent run that did not finish
                raise
        log(f"installed the Meta-World {METAWORLD_VERSION} reach assets in {dest} "
            f"({len(data) / 1e6:.0f} MB wheel, {time.time() - t0:.1f} s)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
