#!/usr/bin/env python3
"""Write crates/envs/assets/dial/dial.xml: the reconstructed Dial scene (docs/dial.md).

The scene is ours. Only numbers come from elsewhere:
  * the Kinova Jaco arm and 3-finger hand kinematic tree (body positions and orientations, link
    masses) from dm_control's `third_party/kinova/{jaco_arm,jaco_hand}.xml` in the PyPI wheel
    `dm-control==1.0.50` (BSD-3-Clause upstream: Copyright (c) 2017 Kinova Robotics inc., modified
    work Copyright (c) 2018 The dm_control Authors; see crates/envs/assets/dial/NOTICE);
  * each body's inertia and the collision primitives (capsules and a box fitted to each mesh's
    bounding box), computed here by MuJoCo from the wheel's decimated meshes. The scene itself has
    no mesh: it needs no download at build or run time;
  * the pad's geometry (phone layout, 12 cm keys on a 14 cm pitch), the joint dynamics (damping,
    armature, frictionloss), the gears and the pedestal from the facts in
    shared/reference/dial.md sec. 2.1 / 6.3 (TACO's Jaco pin-pad), written out here, not copied.

Deliberate changes to dm_control's tree (sec. 6.3): joint 1 and joint 2 turn about -z, so that +q1
turns the arm counter-clockwise seen from above and a negative joint-2 torque lifts the arm (the
original's sign convention, which its action box encodes); arm joints are unlimited; the fingers
keep dm_control's range [0.15, 1.35].

Usage (the wheel from `pip download --no-deps dm-control==1.0.50`; checked against its sha256):
  build_scene.py --wheel dm_control-1.0.50-py3-none-any.whl [--out crates/envs/assets/dial/dial.xml]
Needs: mujoco==3.17.0.
"""
import argparse
import hashlib
import os
import tempfile
import zipfile

import mujoco

WHEEL_SHA256 = "5434e1e51ff69016867426da7df6064b18d140e4d0a628f879bbcf0e7d0a586d"
KINOVA = "dm_control/third_party/kinova/"
MESHES = ["base", "shoulder", "arm", "forearm", "wrist", "hand_3finger_main", "finger_proximal",
          "finger_distal"]
ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))

# (body, parent, pos, quat, joint, [(geom, mesh, mass, fitted primitive)]), dm_control's numbers.
FINGER_QUATS = {
    1: ("0.00279 0.03126 -0.11467", "0.24396 -0.63159 -0.38818 0.62521"),
    2: ("-0.02226 -0.02707 -0.11482", "0.601679 -0.254671 0.659653 -0.37146"),
    3: ("0.02226 -0.02707 -0.11482", "0.659653 -0.37146 0.601679 -0.254671"),
}
BODIES = [
    ("b_base", "world", "0 0 0.25", "1 0 0 0", None, [("base", "base", 0.718306, "cylinder")]),
    ("b_1", "b_base", "0 0 0.15675", "0 0 1 0", "joint_1",
     [("link_1", "shoulder", 0.643205, "capsule")]),
    ("b_2", "b_1", "0 0.0016 -0.11875", "0 0 -0.707107 0.707107", "joint_2",
     [("link_2", "arm", 1.16915, "capsule")]),
    ("b_3", "b_2", "0 -0.41 0", "0 0 1 0", "joint_3", [("link_3", "forearm", 0.673443, "capsule")]),
    ("b_4", "b_3", "0 0.2073 -0.0114", "0 0 -0.707107 0.707107", "joint_4",
     [("link_4", "wrist", 0.221432, "capsule")]),
    ("b_5", "b_4", "0 -0.03703 -0.06414", "0 0 0.5 0.866025", "joint_5",
     [("link_5", "wrist", 0.221432, "capsule")]),
    # dm_control's b_6 carries only a 1e-9 kg ring; the hand is its child.
    ("b_6", "b_5", "0 -0.03703 -0.06414", "0 0 0.5 0.866025", "joint_6", []),
    ("hand", "b_6", "0 0 0", "0 0.70710678118 0.70710678118 0", None,
     [("hand", "hand_3finger_main", 0.54719, "box")]),
]
for k in (1, 2, 3):
    pos, quat = FINGER_QUATS[k]
    BODIES.append((f"b_finger_{k}", "hand", pos, quat, f"finger_{k}",
                   [(f"finger_knuckle_{k}", "finger_proximal", 0.0255204, "capsule")]))
    BODIES.append((f"b_finger_tip_{k}", f"b_finger_{k}", "0.044 -0.003 0", "1 0 0 0", None,
                   [(f"finger_tip_{k}", "finger_distal", 0.0132655, "capsule")]))

# TACO's joint friction (sec. 2.1): arm joints 1-6, then the fingers (none).
FRICTIONLOSS = {"joint_1": 3, "joint_2": 100, "joint_3": 10, "joint_4": 3, "joint_5": 3,
                "joint_6": 3}
GEARS = [("joint_1", 50), ("joint_2", 100), ("joint_3", 100), ("joint_4", 50), ("joint_5", 50),
         ("joint_6", 50), ("finger_1", 10), ("finger_2", 10), ("finger_3", 10)]
# Digit -> key centre (x, y) in the world (sec. 2.1, phone layout).
KEYS = {1: (0.36, 0.21), 2: (0.50, 0.21), 3: (0.64, 0.21), 4: (0.36, 0.07), 5: (0.50, 0.07),
        6: (0.64, 0.07), 7: (0.36, -0.07), 8: (0.50, -0.07), 9: (0.64, -0.07), 0: (0.50, -0.21)}


def g(x):
    return f"{x:.9g}"


def vec(v):
    return " ".join(g(float(x)) for x in v)


def source_xml(meshdir, kind):
    """The tree with mesh geoms (kind='mesh': inertia) or fitted primitives (kind='fit')."""
    out = [f'<mujoco><compiler angle="radian" meshdir="{meshdir}" fitaabb="true"/><asset>']
    out += [f'<mesh name="{m}" file="{m}.stl"/>' for m in MESHES]
    out.append("</asset><worldbody>")
    children = {}
    for b in BODIES:
        children.setdefault(b[1], []).append(b)

    def emit(body):
        name, _, pos, quat, joint, geoms = body
        out.append(f'<body name="{name}" pos="{pos}" quat="{quat}">')
        if joint:
            out.append(f'<joint name="{joint}"/>')
        for gname, mesh, mass, prim in geoms:
            t = "mesh" if kind == "mesh" else prim
            out.append(f'<geom name="{gname}" type="{t}" mesh="{mesh}" mass="{mass}"/>')
        if not geoms and kind == "mesh":
            out.append('<geom type="sphere" size="0.001" mass="1e-9"/>')
        for c in children.get(name, []):
            emit(c)
        out.append("</body>")

    for b in children["world"]:
        emit(b)
    out.append("</worldbody></mujoco>")
    return "".join(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--wheel", required=True)
    ap.add_argument("--out", default=os.path.join(ROOT, "crates/envs/assets/dial/dial.xml"))
    args = ap.parse_args()
    with open(args.wheel, "rb") as f:
        digest = hashlib.sha256(f.read()).hexdigest()
    if digest != WHEEL_SHA256:
        raise SystemExit(f"{args.wheel}: sha256 {digest}, expected {WHEEL_SHA256} (dm-control 1.0.50)")
    with tempfile.TemporaryDirectory() as tmp, zipfile.ZipFile(args.wheel) as zf:
        for m in MESHES:
            zf.extract(f"{KINOVA}meshes_decimated/{m}.stl", tmp)
        meshdir = os.path.join(tmp, KINOVA, "meshes_decimated") + "/"
        inert = mujoco.MjModel.from_xml_string(source_xml(meshdir, "mesh"))
        fit = mujoco.MjModel.from_xml_string(source_xml(meshdir, "fit"))

    lines = []
    w = lines.append
    w("<!-- promptdt's reconstructed Dial scene (docs/dial.md). Written by scripts/dial/build_scene.py:")
    w("     do not edit by hand. The Jaco arm and hand kinematics, masses and the inertias and collision")
    w("     primitives derived from their meshes come from dm_control's third_party/kinova (BSD-3-Clause,")
    w("     Kinova Robotics 2017, The dm_control Authors 2018; see NOTICE beside this file); the pad and the")
    w("     joint dynamics follow the facts of TACO's Jaco pin-pad (shared/reference/dial.md). -->")
    w('<mujoco model="promptdt-dial">')
    w('  <compiler angle="radian" autolimits="true"/>')
    w('  <option timestep="0.002" integrator="Euler" gravity="0 0 -9.81"/>')
    w("  <default>")
    w('    <joint damping="0.2" armature="0.01"/>')
    w('    <geom margin="0.001"/>')
    w('    <default class="robot">')
    w('      <geom contype="1" conaffinity="0" rgba="0.15 0.15 0.15 1"/>')
    w("    </default>")
    w('    <default class="finger">')
    w('      <joint range="0.15 1.35" frictionloss="0"/>')
    w('      <geom contype="1" conaffinity="0" rgba="0.7 0.7 0.7 1"/>')
    w("    </default>")
    w("  </default>")
    w("  <worldbody>")
    w('    <light pos="0.5 0 2" dir="0 0 -1"/>')
    w('    <geom name="floor" type="plane" size="2 2 0.1" contype="0" conaffinity="1" rgba="0.8 0.8 0.8 1"/>')
    w('    <geom name="table" type="box" pos="0.5 0 0" size="0.4 0.4 0.05" contype="1" conaffinity="0" rgba="0.55 0.4 0.25 1"/>')
    w('    <body name="pad" pos="0.5 0 0.05">')
    w('      <geom name="pad" type="box" size="0.22 0.285 0.0495" rgba="0.3 0.3 0.35 1"/>')
    for d in range(10):
        x, y = KEYS[d]
        w(f'      <geom name="key_{d}" type="box" pos="{g(x - 0.5)} {g(y)} 0.04" size="0.06 0.06 0.01" rgba="0.9 0.9 0.9 1"/>')
    w("    </body>")
    w('    <geom name="pedestal" class="robot" type="capsule" fromto="0 0 0 0 0 0.25" size="0.045"/>')

    children = {}
    for b in BODIES:
        children.setdefault(b[1], []).append(b)

    def emit(body, depth):
        name, _, pos, quat, joint, geoms = body
        pad = "  " * depth
        bid = mujoco.mj_name2id(inert, mujoco.mjtObj.mjOBJ_BODY, name)
        cls = ' childclass="finger"' if name.startswith("b_finger") else ""
        w(f'{pad}<body name="{name}" pos="{pos}" quat="{quat}"{cls}>')
        if geoms:
            w(f'{pad}  <inertial pos="{vec(inert.body_ipos[bid])}" quat="{vec(inert.body_iquat[bid])}" '
              f'mass="{g(inert.body_mass[bid])}" diaginertia="{vec(inert.body_inertia[bid])}"/>')
        else:
            # dm_control's b_6: a 1e-9 kg ring, as a point mass so the joint has an inertia.
            w(f'{pad}  <inertial pos="0 0 0" mass="1e-9" diaginertia="1e-12 1e-12 1e-12"/>')
        if joint:
            axis = ' axis="0 0 -1"' if joint in ("joint_1", "joint_2") else ""
            fl = f' frictionloss="{FRICTIONLOSS[joint]}"' if joint in FRICTIONLOSS else ""
            w(f'{pad}  <joint name="{joint}"{axis}{fl}/>')
        for gname, _, _, prim in geoms:
            gid = mujoco.mj_name2id(fit, mujoco.mjtObj.mjOBJ_GEOM, gname)
            size = fit.geom_size[gid][: {"capsule": 2, "cylinder": 2, "box": 3}[prim]]
            c = "" if name.startswith("b_finger") else ' class="robot"'
            w(f'{pad}  <geom name="{gname}"{c} type="{prim}" size="{vec(size)}" '
              f'pos="{vec(fit.geom_pos[gid])}" quat="{vec(fit.geom_quat[gid])}" mass="0"/>')
        for c in children.get(name, []):
            emit(c, depth + 1)
        w(f"{pad}</body>")

    for b in children["world"]:
        emit(b, 2)
    w("  </worldbody>")
    w("  <actuator>")
    for joint, gear in GEARS:
        w(f'    <motor name="{joint}" joint="{joint}" gear="{gear}"/>')
    w("  </actuator>")
    w("</mujoco>")
    text = "\n".join(lines) + "\n"
    mujoco.MjModel.from_xml_string(text)  # it must compile
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    tmp = args.out + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
