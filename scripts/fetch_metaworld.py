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
import os
import sys
import time
import zipfile

from wheel_files import download_checked, install_atomically, read_checked, record_hashes, write_file

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


def populate(tmp):
    """Downloads the wheel and extracts the checked reach assets and licence into `tmp`."""
    log(f"downloading {WHEEL}")
    wheel_path = os.path.join(tmp, WHEEL)
    size = download_checked(WHEEL_URL, WHEEL_SHA256, wheel_path, "fetch_metaworld")
    with zipfile.ZipFile(wheel_path) as zf:
        hashes = record_hashes(zf)
        members = [("metaworld/assets/" + f, os.path.join("assets", f)) for f in ASSET_FILES]
        members.append((LICENSE_MEMBER, "LICENSE"))
        for member, rel in members:
            write_file(os.path.join(tmp, rel), read_checked(zf, hashes, member, "fetch_metaworld", WHEEL))
    os.remove(wheel_path)
    return size


def main():
    root = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "third_party"))
    t0 = time.time()
    size = install_atomically(root, "metaworld", METAWORLD_VERSION, populate)
    if size is not None:
        log(f"installed the Meta-World {METAWORLD_VERSION} reach assets in {os.path.join(root, 'metaworld')} "
            f"({size / 1e6:.0f} MB wheel, {time.time() - t0:.1f} s)")


if __name__ == "__main__":
    main()
