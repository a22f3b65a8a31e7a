#!/usr/bin/env python3
"""Lengths of the Rust functions in `crates/*/src`, for the house rule "no function over ~120
lines outside flat tables": prints every function over the limit (default 120 lines) and the
counts over 120 and over 200.

A brace-matching scan, not a parser: a `fn` item starts at its `fn` line and ends at the brace that
closes its body; strings, chars and comments are skipped so their braces do not count. Functions
without a body (trait declarations) are skipped.

    python3 scripts/fn_lengths.py [--limit N] [ROOT]
"""

import argparse
import re
import sys
from pathlib import Path

FN = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?(?:const\s+)?(?:async\s+)?(?:unsafe\s+)?"
                r"(?:extern\s+\"[^\"]*\"\s+)?fn\s+(\w+)")


def code_only(text):
    """`text` with strings, chars and comments blanked (newlines kept), so braces are code's."""
    out, i, n = [], 0, len(text)
    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(" " * (j - i))
            i = j
        elif text.startswith("/*", i):
            j = text.find("*/", i + 2)
            j = n if j < 0 else j + 2
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == "r" and re.match(r'r(#*)"', text[i:i + 10]) and not (i and text[i - 1].isalnum()):
            hashes = re.match(r'r(#*)"', text[i:]).group(1)
            end = '"' + hashes
            j = text.find(end, i + 2 + len(hashes))
            j = n if j < 0 else j + len(end)
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            out.append(re.sub(r"[^\n]", " ", text[i:j + 1]))
            i = j + 1
        elif c == "'" and re.match(r"'(\\.|[^\\'])'|'\\u\{[0-9a-fA-F]+\}'|'\\x[0-9a-fA-F]{2}'", text[i:]):
            m = re.match(r"'(\\.|[^\\'])'|'\\u\{[0-9a-fA-F]+\}'|'\\x[0-9a-fA-F]{2}'", text[i:])
            out.append(" " * len(m.group(0)))
            i += len(m.group(0))
        else:
            out.append(c)
            i += 1
    return "".join(out)


def functions(path):
    """(name, first line, length in lines) of every function with a body in `path`."""
    lines = code_only(path.read_text()).split("\n")
    found = []
    for start, line in enumerate(lines):
        m = FN.match(line)
        if not m:
            continue
        depth, opened = 0, False
        for end in range(start, len(lines)):
            for ch in lines[end]:
                if ch == "{":
                    depth, opened = depth + 1, True
                elif ch == "}":
                    depth -= 1
                elif ch == ";" and not opened and depth == 0:
                    break
            else:
                if opened and depth == 0:
                    found.append((m.group(1), start + 1, end - start + 1))
                    break
                continue
            break
    return found


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", nargs="?", default=".")
    ap.add_argument("--limit", type=int, default=120)
    a = ap.parse_args()
    root = Path(a.root)
    rows = []
    for f in sorted(root.glob("crates/*/src/**/*.rs")):
        for name, line, length in functions(f):
            rows.append((length, f"{f.relative_to(root)}:{line}", name))
    rows.sort(reverse=True)
    for length, where, name in rows:
        if length > a.limit:
            print(f"{length:5} {where} {name}")
    over = lambda k: sum(1 for r in rows if r[0] > k)
    print(f"{len(rows)} functions; over 120 lines: {over(120)}; over 200 lines: {over(200)}")


if __name__ == "__main__":
    sys.exit(main())
