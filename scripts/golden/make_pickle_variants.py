#!/usr/bin/env python3
"""Writes the small pickle fixtures that crates/data/tests/pickle_*.rs read.

Run with the project's venv (numpy 2.x):

    .venv/bin/python scripts/golden/make_pickle_variants.py

Output, in crates/data/tests/fixtures/pickle/:

- `ref-*.pkl`: files in the reference release's layout (a list of dicts of numpy arrays), each one
  exercising one thing the Rust reader must accept: every pickle protocol 2..5, numpy 1.x and 2.x
  module names, float64 arrays, `dones` instead of `terminals`, rewards of shape (T,), Fortran-order
  and big-endian arrays, protocol-5 in-band buffers (writable and read-only).
- `generic-p{2,3,4,5}.pkl`: one dict holding every Python and numpy value the parser must
  understand.
- `err-*.pkl` / hostile files: inputs the reader must refuse, with the error it must give. The
  hostile ones that would run code are assembled opcode by opcode and are never unpickled here.
- `variants.json`: what each file must load to (or the error it must give).
- `corpus/`: seeds and edge cases for the robustness tests (`ok-*` must parse, `err-*` must fail).

The output is deterministic (fixed seeds), so re-running the script reproduces the same bytes.
"""

import json
import pickle
import pickletools
import struct
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "crates" / "data" / "tests" / "fixtures" / "pickle"
CORPUS = OUT / "corpus"

OBS_DIM, ACT_DIM = 3, 2

manifest = []


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def write(name: str, data: bytes) -> None:
    # Keep every fixture small: they are checked into the tree and read by fast unit tests.
    assert len(data) < 16_384, f"{name} is {len(data)} bytes; fixtures should be a few KB"
    (OUT / name).write_bytes(data)


def f32_list(a) -> list:
    """Values as the Rust reader must produce them: float32, C order, flattened."""
    return [float(x) for x in np.asarray(a, dtype=np.float32).reshape(-1)]


def le_c_bytes(a: np.ndarray) -> str:
    """The array's bytes as the Rust NdArray holds them after `to_c_order()`: little-endian,
    C order."""
    return np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"))).tobytes(order="C").hex()


def renumber_numpy1(data: bytes, proto: int) -> bytes:
    """Rewrites numpy 2 module names (`numpy._core.*`) to numpy 1.x ones (`numpy.core.*`).

    numpy 1.x writes `numpy.core.multiarray._reconstruct`, `numpy.core.multiarray.scalar` and
    `numpy.core.numeric._frombuffer`; numpy 2 writes `numpy._core...`. Only numpy 2 is installed, so
    the numpy 1.x spelling is produced by editing the bytes. Protocols 2 and 3 name globals with the
    newline-terminated GLOBAL opcode; protocols 4 and 5 push the names with SHORT_BINUNICODE (length
    byte in front) and use STACK_GLOBAL, and their FRAME lengths change with the edit, so those are
    re-framed by `pickletools.optimize`.
    """
    if proto < 4:
        pairs = [
            (b"numpy._core.multiarray\n", b"numpy.core.multiarray\n"),
            (b"numpy._core.numeric\n", b"numpy.core.numeric\n"),
        ]
    else:
        pairs = [
            (b"\x8c\x16numpy._core.multiarray", b"\x8c\x15numpy.core.multiarray"),
            (b"\x8c\x13numpy._core.numeric", b"\x8c\x12numpy.core.numeric"),
        ]
    out = data
    for old, new in pairs:
        out = out.replace(old, new)
    assert out != data, "nothing to rename"
    assert b"numpy._core" not in out
    if proto >= 4:
        out = pickletools.optimize(out)
    # Safe to unpickle: we wrote it from our own numpy data a moment ago. numpy 2 still provides the
    # `numpy.core` names for exactly this purpose (reading numpy 1.x pickles), with a warning.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        back = pickle.loads(out)
    assert equal_values(back, pickle.loads(data)), "renamed pickle loads differently"
    return out


def equal_values(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            # numpy 2 reads a big-endian pickle back as native-endian: compare kind and size only.
            and a.dtype.name == b.dtype.name
            and a.shape == b.shape
            and np.array_equal(a, b)
        )
    if isinstance(a, dict):
        return (
            isinstance(b, dict)
            and list(a) == list(b)
            and all(equal_values(a[k], b[k]) for k in a)
        )
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(map(equal_values, a, b))
    return type(a) is type(b) and a == b


def opcodes(data: bytes) -> set:
    return {op.name for op, _, _ in pickletools.genops(data)}


# ---------------------------------------------------------------------------------------------
# Reference-layout files (list of dicts of arrays)
# ---------------------------------------------------------------------------------------------


def make_trajs(seed, lengths=(5, 3), flags_last=(True, True), float_dtype="<f4"):
    rng = np.random.default_rng(seed)
    trajs = []
    for t_len, flag in zip(lengths, flags_last):
        obs = rng.standard_normal((t_len + 1, OBS_DIM)).astype(float_dtype)
        traj = {
            "observations": obs[:-1].copy(),
            "next_observations": obs[1:].copy(),
            "actions": rng.uniform(-1, 1, (t_len, ACT_DIM)).astype(float_dtype),
            "rewards": rng.standard_normal((t_len, 1)).astype(float_dtype),
            "terminals": np.zeros((t_len, 1), dtype=bool),
        }
        traj["terminals"][-1, 0] = flag
        trajs.append(traj)
    return trajs


def expected_flags(flags: np.ndarray, horizon: int):
    """The reader's rule for `TerminalsAs::Auto { horizon }`, written out independently.

    A flag on the last step of a trajectory of exactly `horizon` steps is a time limit (truncated);
    any other flag is a real end (terminated). A trajectory without a flag on its last step is
    marked truncated there (it was cut; nothing says the MDP ended).
    """
    t_len = len(flags)
    terminated = [False] * t_len
    truncated = [False] * t_len
    for t, f in enumerate(flags):
        if f:
            if t == t_len - 1 and t_len == horizon:
                truncated[t] = True
            else:
                terminated[t] = True
    if not flags[-1]:
        truncated[-1] = True
    return terminated, truncated


def describe_ref(name, trajs, horizon, notes, proto_ops=None):
    out = []
    for traj in trajs:
        term_key = "terminals" if "terminals" in traj else "dones"
        flags = np.asarray(traj[term_key]).reshape(-1).astype(bool)
        terminated, truncated = expected_flags(flags, horizon)
        out.append(
            {
                "observations": f32_list(traj["observations"]),
                "actions": f32_list(traj["actions"]),
                "rewards": f32_list(traj["rewards"]),
                "terminated": terminated,
                "truncated": truncated,
            }
        )
    first = trajs[0]
    arrays = [
        {"key": k, "dtype": v.dtype.name, "shape": list(v.shape)}
        for k, v in first.items()
        if isinstance(v, np.ndarray)
    ]
    entry = {
        "file": name,
        "kind": "reference",
        "horizon": horizon,
        "obs_dim": OBS_DIM,
        "act_dim": ACT_DIM,
        "trajectories": out,
        "arrays": arrays,
        "notes": notes,
    }
    if proto_ops:
        entry["opcodes"] = sorted(proto_ops)
    manifest.append(entry)


def ref_variant(name, trajs, proto, notes, horizon=5, numpy1=False, **dump_kw):
    data = pickle.dumps(trajs, protocol=proto, **dump_kw)
    if numpy1:
        data = renumber_numpy1(data, proto)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpy.core.* names warn on numpy 2
        assert equal_values(pickle.loads(data), trajs)
    write(name, data)
    describe_ref(name, trajs, horizon, notes, opcodes(data))
    return data


def make_reference_files():
    base = make_trajs(1)
    for proto in (2, 3, 4, 5):
        ref_variant(f"ref-p{proto}.pkl", base, proto, f"numpy 2 names, protocol {proto}")
        ref_variant(
            f"ref-p{proto}-numpy1.pkl",
            base,
            proto,
            f"numpy 1.x names (numpy.core.*), protocol {proto}",
            numpy1=True,
        )

    # Protocol 5 without buffer_callback: contiguous arrays go in-band through _frombuffer; a
    # writable array becomes BYTEARRAY8, a read-only one BINBYTES.
    ro = make_trajs(2)
    for traj in ro:
        for v in traj.values():
            v.flags.writeable = False
    data = ref_variant(
        "ref-p5-readonly.pkl", ro, 5, "protocol 5, read-only arrays: in-band BINBYTES"
    )
    assert "BYTEARRAY8" not in opcodes(data)

    # Non-contiguous arrays are pickled by _reconstruct even under protocol 5.
    strided = make_trajs(3)
    for traj in strided:
        for k in ("observations", "actions"):
            wide = np.repeat(traj[k], 2, axis=1)
            traj[k] = wide[:, ::2]
            assert not traj[k].flags.c_contiguous and not traj[k].flags.f_contiguous
    ref_variant(
        "ref-p5-strided.pkl", strided, 5, "protocol 5, non-contiguous arrays (_reconstruct)"
    )

    ref_variant(
        "ref-float64.pkl", make_trajs(4, float_dtype="<f8"), 4, "float64 arrays (read as float32)"
    )

    dones = make_trajs(5)
    for traj in dones:
        traj["dones"] = traj.pop("terminals")
    ref_variant("ref-dones.pkl", dones, 4, "key `dones` instead of `terminals`")

    flat = make_trajs(6)
    for traj in flat:
        traj["rewards"] = traj["rewards"].reshape(-1)
        traj["terminals"] = traj["terminals"].reshape(-1)
        del traj["next_observations"]
    ref_variant(
        "ref-flat.pkl", flat, 4, "rewards and terminals of shape (T,), no next_observations"
    )

    fortran = make_trajs(7)
    for traj in fortran:
        traj["observations"] = np.asfortranarray(traj["observations"])
        traj["actions"] = np.asfortranarray(traj["actions"])
    ref_variant("ref-fortran-p4.pkl", fortran, 4, "Fortran-order arrays via _reconstruct")
    ref_variant("ref-fortran-p5.pkl", fortran, 5, "Fortran-order arrays via _frombuffer order F")

    big = make_trajs(8, float_dtype=">f4")
    ref_variant("ref-bigendian.pkl", big, 4, "big-endian float32 arrays (byte-swapped on read)")

    # Terminal handling: lengths 5 (== horizon), 3 and 4; the first ends at the horizon (time
    # limit), the second ends early with a flag (a real termination), the third has no flag.
    ends = make_trajs(9, lengths=(5, 3, 4), flags_last=(True, True, False))
    ref_variant("ref-terminals.pkl", ends, 4, "time limit, early termination, unflagged end")


# ---------------------------------------------------------------------------------------------
# Generic values
# ---------------------------------------------------------------------------------------------


def enc(v):
    """Tagged JSON form of the value tree the Rust parser must return."""
    if v is None:
        return ["none"]
    if isinstance(v, bool):
        return ["bool", v]
    if isinstance(v, np.generic):
        a = np.asarray(v)
        return ["nd", a.dtype.name, [], False, le_c_bytes(a)]
    if isinstance(v, int):
        return ["int", v]
    if isinstance(v, float):
        return ["float", v]
    if isinstance(v, str):
        return ["str", v]
    if isinstance(v, (bytes, bytearray)):
        return ["bytes", bytes(v).hex()]
    if isinstance(v, list):
        return ["list", [enc(x) for x in v]]
    if isinstance(v, tuple):
        return ["tuple", [enc(x) for x in v]]
    if isinstance(v, dict):
        return ["dict", [[enc(k), enc(x)] for k, x in v.items()]]
    if isinstance(v, np.ndarray):
        # Fortran-order arrays keep their layout through the parser; anything else arrives in C
        # order (numpy writes non-contiguous and 'K'-order arrays out in a C layout or
        # materialises them).
        fortran = bool(v.flags.f_contiguous and not v.flags.c_contiguous)
        return ["nd", v.dtype.name, list(v.shape), fortran, le_c_bytes(v)]
    raise TypeError(type(v))


def generic_value(proto):
    v = {
        "none": None,
        "true": True,
        "false": False,
        "ints": [0, 1, -1, 255, 256, 65535, 65536, -(2**31), 2**31 - 1, 2**31, 2**40]
        + [-(2**63), 2**63 - 1],
        "floats": [1.25, -3.5e-7, 0.0, 1e300],
        "str": "héllo ✓",
        "empty_str": "",
        "bytes": b"\x00\x01\xff",
        "empty_bytes": b"",
        "tuples": [(), (1,), (1, 2), (1, 2, 3), (1, 2, 3, 4, 5)],
        "nested": [[1, [2, (3, {"k": None})]], {}],
        "int_keys": {1: "one", (2, "two"): "pair", None: "none"},
        "f32": (np.arange(6, dtype="<f4").reshape(2, 3) / 4).astype("<f4"),
        "f64": np.array([[1.5, -2.25], [1e-300, 3.0]], dtype="<f8"),
        "b1": np.array([True, False, True]),
        "i1": np.array([-128, 0, 127], dtype="i1"),
        "i2": np.array([-32768, 5], dtype="<i2"),
        "i4": np.array([[1, -2], [3, 2**31 - 1]], dtype="<i4"),
        "i8": np.array([-(2**63), 2**63 - 1], dtype="<i8"),
        "u1": np.array([0, 200, 255], dtype="u1"),
        "u2": np.array([65535], dtype="<u2"),
        "u4": np.array([2**32 - 1], dtype="<u4"),
        "u8": np.array([2**64 - 1], dtype="<u8"),
        "big_f8": np.array([1.5, -2.0, 1e-10], dtype=">f8"),
        "big_i4": np.array([1, -2, 70000], dtype=">i4"),
        "fortran": np.asfortranarray(np.arange(24, dtype="<f4").reshape(2, 3, 4)),
        "strided": np.arange(10, dtype="<i8")[::3],
        # numpy 2 pickles this (contiguous in a permuted axis order) as _frombuffer(..., 'K', axes).
        "permuted": np.arange(24, dtype="<i4").reshape(2, 3, 4).transpose(2, 0, 1),
        "empty_arr": np.zeros((0, 3), dtype="<f4"),
        "zero_d": np.array(2.5, dtype="<f8"),
        "scalar_f32": np.float32(1.5),
        "scalar_f64": np.float64(-2.25),
        "scalar_i64": np.int64(-7),
        "scalar_bool": np.bool_(True),
        "shared": None,
    }
    arr = np.array([1.0, 2.0], dtype="<f4")
    # The same object twice: the second is a memo lookup (BINGET) in the pickle.
    v["shared"] = [arr, arr]
    if proto >= 5:
        v["bytearray"] = bytearray(b"\x10\x20")
    return v


def make_generic_files():
    for proto in (2, 3, 4, 5):
        value = generic_value(proto)
        name = f"generic-p{proto}.pkl"
        data = pickle.dumps(value, protocol=proto)
        write(name, data)
        manifest.append(
            {
                "file": name,
                "kind": "generic",
                "value": enc(value),
                "opcodes": sorted(opcodes(data)),
                "notes": f"every supported value kind, protocol {proto}",
            }
        )
    # numpy 1.x scalar and _frombuffer names.
    for proto in (2, 5):
        value = {"scalar": np.float32(0.5), "arr": np.arange(3, dtype="<f4")}
        name = f"generic-p{proto}-numpy1.pkl"
        data = renumber_numpy1(pickle.dumps(value, protocol=proto), proto)
        write(name, data)
        manifest.append(
            {
                "file": name,
                "kind": "generic",
                "value": enc(value),
                "opcodes": sorted(opcodes(data)),
                "notes": f"numpy.core.* names (scalar, _reconstruct, _frombuffer), proto {proto}",
            }
        )


# ---------------------------------------------------------------------------------------------
# Files that must be refused
# ---------------------------------------------------------------------------------------------


def short_str(s: str) -> bytes:
    b = s.encode()
    return b"\x8c" + bytes([len(b)]) + b


def error_file(name, data, layer, contains, notes):
    """layer: "pickle" (parse must fail) or "reference" (parses, but is not a valid dataset)."""
    write(name, data)
    manifest.append(
        {"file": name, "kind": "error", "layer": layer, "error_contains": contains, "notes": notes}
    )


def make_error_files():
    # Calls os.system('echo pwned') if unpickled by Python. Assembled by hand; never loaded here.
    os_system = (
        b"\x80\x02"
        + b"cos\nsystem\n"
        + b"X" + struct.pack("<I", 10) + b"echo pwned"
        + b"\x85"  # TUPLE1
        + b"R"  # REDUCE
        + b"."
    )
    error_file(
        "err-os-system.pkl",
        os_system,
        "pickle",
        ["global os.system is not allowed", "byte 2"],
        "GLOBAL os.system + REDUCE",
    )

    # builtins.eval through STACK_GLOBAL, hidden inside a list of dicts like a real file.
    ev = (
        b"\x80\x04"
        + b"]"  # EMPTY_LIST
        + b"}"  # EMPTY_DICT
        + short_str("observations")
        + short_str("builtins")
        + short_str("eval")
        + b"\x93"  # STACK_GLOBAL
        + short_str("1+1")
        + b"\x85R"  # TUPLE1 REDUCE
        + b"s"  # SETITEM
        + b"a"  # APPEND
        + b"."
    )
    error_file(
        "err-builtins-eval.pkl",
        ev,
        "pickle",
        ["global builtins.eval is not allowed", "STACK_GLOBAL"],
        "STACK_GLOBAL builtins.eval inside a trajectory dict",
    )

    # A valid file cut in the middle of an array's raw bytes.
    full = pickle.dumps(make_trajs(1), protocol=4)
    cut_op = None
    for op, arg, pos in pickletools.genops(full):
        if op.name in ("SHORT_BINBYTES", "BINBYTES") and len(arg) > 20:
            cut_op = (op.name, pos, len(arg))
            break
    assert cut_op is not None
    name, pos, n = cut_op
    header = 2 if name == "SHORT_BINBYTES" else 5
    cut = full[: pos + header + n // 2]
    left = len(cut) - (pos + header)
    error_file(
        "err-truncated.pkl",
        cut,
        "pickle",
        [f"truncated at byte {pos} while reading {name} length {n}: {left} bytes left"],
        "a valid protocol-4 file cut inside an array's bytes",
    )

    obj = [{"observations": np.array([1.0, "x", None], dtype=object)}]
    error_file(
        "err-object-array.pkl",
        pickle.dumps(obj, protocol=4),
        "pickle",
        ["numpy.dtype('O8')", "object arrays are not supported"],
        "a dict holding an object array",
    )

    huge = b"\x80\x04\x8e" + struct.pack("<Q", 1 << 60) + b"abc."
    error_file(
        "err-huge-binbytes8.pkl",
        huge,
        "pickle",
        [f"truncated at byte 2 while reading BINBYTES8 length {1 << 60}: 4 bytes left"],
        "a BINBYTES8 claiming 2^60 bytes",
    )

    buffers = []
    oob = pickle.dumps(np.arange(4.0), protocol=5, buffer_callback=buffers.append)
    assert "NEXT_BUFFER" in opcodes(oob)
    error_file("err-out-of-band.pkl", oob, "pickle", ["NEXT_BUFFER", "not supported"],
               "protocol 5 with an out-of-band buffer (the buffer is not in the file)")

    # Parse fine, but are not valid reference datasets.
    bad_act = make_trajs(10)
    bad_act[1]["actions"] = np.zeros((3, ACT_DIM + 1), dtype="<f4")
    error_file(
        "err-act-dim.pkl",
        pickle.dumps(bad_act, protocol=4),
        "reference",
        ["trajectory 1: `actions` has shape (3, 3), expected (3, 2)"],
        "act_dim differs between trajectories",
    )

    nan = make_trajs(11)
    nan[1]["observations"][2, 1] = np.nan
    error_file("err-nan.pkl", pickle.dumps(nan, protocol=4), "reference",
               ["trajectory 1: `observations`", "not finite"], "NaN in observations")

    inf = make_trajs(12, float_dtype="<f8")
    inf[0]["rewards"][1, 0] = 1e300  # finite in float64, infinite once read as float32
    error_file("err-f64-overflow.pkl", pickle.dumps(inf, protocol=4), "reference",
               ["trajectory 0: `rewards`", "not finite"], "float64 reward out of float32 range")

    missing = make_trajs(13)
    del missing[0]["actions"]
    error_file("err-missing-actions.pkl", pickle.dumps(missing, protocol=4), "reference",
               ["trajectory 0: no `actions`"], "no actions array")

    both = make_trajs(14)
    for traj in both:
        del traj["terminals"]
    error_file("err-no-terminals.pkl", pickle.dumps(both, protocol=4), "reference",
               ["trajectory 0: no `terminals` or `dones`"], "neither terminals nor dones")

    length = make_trajs(15)
    length[0]["rewards"] = length[0]["rewards"][:-1]
    error_file("err-length.pkl", pickle.dumps(length, protocol=4), "reference",
               ["trajectory 0: `rewards` has shape (4, 1), expected (5,) or (5, 1)"],
               "rewards shorter than observations")

    error_file("err-not-a-list.pkl", pickle.dumps({"observations": 1}, protocol=4), "reference",
               ["expected a list of trajectories, got dict"], "top level is a dict")


# ---------------------------------------------------------------------------------------------
# Robustness corpus
# ---------------------------------------------------------------------------------------------


def corpus(name, data):
    assert name.startswith(("ok-", "err-")), name
    (CORPUS / name).write_bytes(data)


def binput(i):
    return b"q" + bytes([i]) if i < 256 else b"r" + struct.pack("<I", i)


def binget(i):
    return b"h" + bytes([i]) if i < 256 else b"j" + struct.pack("<I", i)


def make_corpus():
    CORPUS.mkdir(parents=True, exist_ok=True)
    corpus("ok-none.bin", b"\x80\x02N.")
    corpus("ok-long-binput-max.bin", b"\x80\x02Nr\xff\xff\xff\xffj\xff\xff\xff\xff\x86.")
    corpus("ok-binbytes8.bin", b"\x80\x04\x8e" + struct.pack("<Q", 3) + b"abc.")
    corpus("ok-binunicode8.bin", b"\x80\x04\x8d" + struct.pack("<Q", 2) + b"hi.")
    corpus("ok-long4.bin", b"\x80\x02\x8b" + struct.pack("<i", 2) + b"\x01\x80.")
    corpus("ok-pop-dup.bin", b"\x80\x02(NN1K\x052\x86.")
    corpus("ok-trailing-bytes.bin", b"\x80\x02K\x07.garbage after STOP is ignored, as Python does")
    # A list that contains itself; only a cycle-aware reader terminates.
    corpus("err-cycle.bin", b"\x80\x02]q\x00h\x00a.")
    # 20k nested lists: deeper than any data file, must fail without overflowing the Rust stack.
    depth = 20_000
    corpus("err-deep-nesting.bin", b"\x80\x02" + b"]" * depth + b"a" * (depth - 1) + b".")
    # "Billion laughs": each level is a list holding the previous level twice (by memo), so the
    # expanded tree has 2^60 leaves.
    laughs = b"\x80\x02]N" + b"a" + binput(0) + b"0"  # POP: only the memo keeps each level
    for i in range(60):
        laughs += b"](" + binget(i) + binget(i) + b"e" + binput(i + 1) + b"0"
    corpus("err-billion-laughs.bin", laughs + binget(60) + b".")
    # One 16 KiB buffer reused by 2000 _frombuffer calls: 32 MB of arrays from a 44 KB file.
    amp = b"\x80\x05\x8c\x13numpy._core.numeric\x8c\x0b_frombuffer\x93\x94"  # memo 0
    amp += b"\x96" + struct.pack("<Q", 16384) + b"\x00" * 16384 + b"\x94"  # memo 1
    # numpy.dtype('u1') with state (3, '|', ...): memo 2
    amp += b"\x8c\x05numpy\x8c\x05dtype\x93\x8c\x02u1\x89\x88\x87R"
    amp += b"(K\x03\x8c\x01|NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb\x94"
    amp += b"M\x00\x40\x85\x94"  # (16384,) memo 3
    amp += b"\x8c\x01C\x94"  # memo 4
    amp += b"]("
    for _ in range(2000):
        amp += b"h\x00(h\x01h\x02h\x03h\x04tR"
    amp += b"e."
    corpus("err-frombuffer-amplify.bin", amp)
    corpus("err-huge-binunicode.bin", b"\x80\x02X\xff\xff\xff\xffabc.")
    corpus("err-huge-long4.bin", b"\x80\x02\x8b\xff\xff\xff\x7f\x01.")
    corpus("err-negative-long4.bin", b"\x80\x02\x8b\xff\xff\xff\xff\x01.")
    corpus("err-wide-long1.bin", b"\x80\x02\x8a\x09" + b"\x01" * 9 + b".")
    # FRAME lengths are a buffering hint and are not checked (see pickle.rs), so this parses.
    corpus("ok-frame-length-ignored.bin", b"\x80\x04\x95" + struct.pack("<Q", 1 << 62) + b"N.")
    corpus("err-binget-missing.bin", b"\x80\x02h\x05.")
    corpus("err-stop-empty.bin", b"\x80\x02.")
    corpus("err-stop-two-items.bin", b"\x80\x02NN.")
    corpus("err-unclosed-mark.bin", b"\x80\x02(N.")
    corpus("err-appends-no-mark.bin", b"\x80\x02]Ne.")
    corpus("err-pop-across-mark.bin", b"\x80\x02N(\x85.")
    corpus("err-setitems-odd.bin", b"\x80\x02}(Nu.")
    corpus("err-unknown-opcode.bin", b"\x80\x02\xff.")
    corpus("err-proto-6.bin", b"\x80\x06N.")
    corpus("err-empty.bin", b"")
    corpus("err-inst.bin", b"\x80\x02(i__main__\nFoo\n.")
    corpus("err-newobj.bin", b"\x80\x02cnumpy\nndarray\n)\x81.")
    corpus("err-global-no-newline.bin", b"\x80\x02cnumpy\nndarr")
    corpus("err-global-as-value.bin", b"\x80\x02cnumpy\nndarray\n.")
    corpus("err-reduce-non-tuple.bin", b"\x80\x02c_codecs\nencode\nNR.")
    corpus(
        "err-codecs-non-latin1.bin",
        b"\x80\x02c_codecs\nencode\n"
        + b"X\x01\x00\x00\x00a"
        + b"X\x05\x00\x00\x00utf-8"
        + b"\x86R.",
    )

    # Hand-assembled numpy arrays (protocol 3 opcodes) for the size and state edge cases.
    # numpy.dtype('f4', False, True), then BUILD with (3, '<', None, None, None, -1, -1, 0).
    dtype_f4_bare = b"cnumpy\ndtype\n" + b"X\x02\x00\x00\x00f4" + b"\x89\x88\x87R"
    dtype_state = b"(K\x03X\x01\x00\x00\x00<NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb"
    dtype_f4 = dtype_f4_bare + dtype_state
    # _reconstruct(numpy.ndarray, (0,), b'b'), waiting for its BUILD.
    recon = b"cnumpy._core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R"

    def state(shape: bytes, data: bytes, dtype: bytes = dtype_f4) -> bytes:
        """BUILD with (1, shape, dtype, False, data); `shape` is the opcodes pushing a tuple."""
        return b"(K\x01" + shape + dtype + b"\x89C" + bytes([len(data)]) + data + b"tb"

    one = b"K\x01\x85"  # (1,)
    # Shape claims 2^30 x 2^30 float32 elements (4 EiB) for 8 bytes of data: the size check
    # must refuse it before anything is allocated.
    big = b"J\x00\x00\x00\x40"
    corpus(
        "err-shape-mismatch.bin",
        b"\x80\x03" + recon + state(big + big + b"\x86", bytes(8)) + b".",
    )
    # 2^62 - 1 squared overflows 64 bits: the multiplication itself must be checked.
    overflow = b"\x8a\x08\xff\xff\xff\xff\xff\xff\xff\x3f"
    corpus(
        "err-shape-overflow.bin",
        b"\x80\x03" + recon + state(overflow + overflow + b"\x86", bytes(8)) + b".",
    )
    minus_one = b"J\xff\xff\xff\xff\x85"  # (-1,)
    corpus("err-negative-shape.bin", b"\x80\x03" + recon + state(minus_one, b"") + b".")
    corpus("err-pending-array.bin", b"\x80\x03" + recon + b".")
    zeros = bytes(4)
    corpus(
        "err-build-twice.bin",
        b"\x80\x03" + recon + state(one, zeros) + state(one, zeros) + b".",
    )
    corpus("ok-reconstruct.bin", b"\x80\x03" + recon + state(one, b"\x00\x00\x80?") + b".")
    # A dtype without its BUILD state: byte order unknown for a multi-byte type.
    corpus(
        "err-dtype-no-state.bin",
        b"\x80\x03" + recon + state(one, b"\x00\x00\x80?", dtype=dtype_f4_bare) + b".",
    )
    corpus("err-structured-dtype.bin", b"\x80\x02cnumpy\ndtype\nX\x02\x00\x00\x00V8\x89\x88\x87R.")
    corpus("err-float16.bin", b"\x80\x02cnumpy\ndtype\nX\x02\x00\x00\x00f2\x89\x88\x87R.")
    corpus("err-bad-utf8.bin", b"\x80\x04\x8c\x02\xff\xfe.")
    corpus("err-unhashable-key.bin", b"\x80\x02}]Ns.")
    corpus("ok-duplicate-key.bin", b"\x80\x02}(K\x01K\x02K\x01K\x03u.")
    # Seeds for mutation: one of each protocol.
    for proto in (2, 3, 4, 5):
        corpus(f"ok-seed-ref-p{proto}.bin", (OUT / f"ref-p{proto}.pkl").read_bytes())


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    CORPUS.mkdir(parents=True, exist_ok=True)
    make_reference_files()
    make_generic_files()
    make_error_files()
    make_corpus()
    # One entry per line: diffs stay readable without one line per float.
    lines = ",\n".join(json.dumps(entry) for entry in manifest)
    (OUT / "variants.json").write_text("[\n" + lines + "\n]\n")
    total = sum(p.stat().st_size for p in OUT.glob("*.pkl"))
    n_corpus = len(list(CORPUS.iterdir()))
    print(f"wrote {len(manifest)} fixtures ({total} bytes) and {n_corpus} corpus files to {OUT}")


if __name__ == "__main__":
    main()
