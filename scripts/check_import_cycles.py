#!/usr/bin/env python3
"""Import circles between the files of each crate: file A naming something in file B
(`use crate::b::..`, `super::b::..`, `self::b`, a child module by name, or an inline
`crate::b::x` path) while B names something in A. A module naming its own ancestors (`super::X`,
`crate::Error` re-exported from lib.rs) is the normal Rust layout and is not counted; the check is
between files neither of which contains the other.

Usage: scripts/check_import_cycles.py [crates-dir]. Exit status 1 when a circle is found."""
import re
import sys
from pathlib import Path

USE = re.compile(r"\buse\s+([^;]+);", re.S)
INLINE = re.compile(r"\b(crate|super|self)((?:::\w+)+)")


def strip_comments(text):
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


TEST_MOD = re.compile(r"#\[cfg\(test\)\]\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+\w+\s*\{")


def split_tests(text):
    """(library code, `#[cfg(test)] mod .. { }` bodies): a unit-test module's imports are reported
    apart, since they are not part of the library's layering."""
    lib, tests, pos = "", "", 0
    for m in TEST_MOD.finditer(text):
        if m.start() < pos:
            continue
        depth, i = 1, m.end()
        while i < len(text) and depth:
            depth += {"{": 1, "}": -1}.get(text[i], 0)
            i += 1
        lib += text[pos : m.start()]
        tests += text[m.end() : i]
        pos = i
    return lib + text[pos:], tests


def paths_in(text):
    paths = []
    for m in USE.finditer(text):
        paths += expand(m.group(1))
    return paths + [m.group(1) + m.group(2) for m in INLINE.finditer(text)]


def expand(tree):
    """`a::{b, c::{d, e}}` -> ['a::b', 'a::c::d', 'a::c::e']."""
    tree = re.sub(r"\s+", "", tree)
    i = tree.find("{")
    if i < 0:
        return [re.sub(r"\bas\w+$", "", tree)]
    prefix, body = tree[:i], tree[i + 1 : tree.rindex("}")]
    parts, depth, cur = [], 0, ""
    for ch in body:
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
            continue
        depth += ch == "{"
        depth -= ch == "}"
        cur += ch
    parts.append(cur)
    out = []
    for p in parts:
        if p:
            for e in expand(p):
                out.append(prefix + e if e != "self" else prefix.rstrip(":"))
    return out


def modules(src):
    """Module path (tuple) -> file, and file -> (module path, is it a directory module)."""
    mods = {}
    for f in src.rglob("*.rs"):
        rel = f.relative_to(src).with_suffix("").parts
        if rel in (("lib",), ("main",)):
            mods[()] = f
        elif rel[-1] == "mod":
            mods[rel[:-1]] = f
        elif "bin" not in rel[:1]:
            mods[rel] = f
    return mods


def resolve(path, here, mods):
    segs = [s for s in path.split("::") if s]
    if not segs:
        return None
    if segs[0] == "crate":
        base, segs = (), segs[1:]
    elif segs[0] in ("super", "self"):
        base = here
        while segs and segs[0] in ("super", "self"):
            if segs[0] == "super":
                base = base[:-1]
            segs = segs[1:]
    elif here + (segs[0],) in mods:
        base = here
    else:
        return None
    best = base if base in mods else None
    for k in range(1, len(segs) + 1):
        if base + tuple(segs[:k]) in mods:
            best = base + tuple(segs[:k])
    return best


def main():
    root = Path(sys.argv[1] if len(sys.argv) > 1 else "crates")
    found = 0
    for src in sorted(root.glob("*/src")):
        mods = modules(src)
        edges, lib_edges = {}, {}
        for mod, f in mods.items():
            lib, tests = split_tests(strip_comments(f.read_text()))
            for text, kinds in ((lib, (edges, lib_edges)), (tests, (edges,))):
                for p in paths_in(text):
                    target = resolve(p, mod, mods)
                    # Ancestors and descendants contain each other; only unrelated files count.
                    if target is None or target[: len(mod)] == mod or mod[: len(target)] == target:
                        continue
                    for e in kinds:
                        e.setdefault(mod, set()).add(target)
        for a, targets in sorted(edges.items()):
            for b in sorted(targets):
                if a < b and a in edges.get(b, ()):
                    found += 1
                    lib_only = b in lib_edges.get(a, ()) and a in lib_edges.get(b, ())
                    where = "" if lib_only else " (through a #[cfg(test)] module)"
                    print(f"circle: {mods[a]} <-> {mods[b]}{where}")
    print(f"{found} import circle(s) between files")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
