"""Lengths of the C functions of the compiled kernel (mkv_env/_fastsim.c and mkv_env/_native/).

Prints every function with its length in lines (from the line of its name in the signature to
its closing brace), longest first, and exits 1 when one is LIMIT (150) lines or longer::

    python scripts/c_function_lengths.py [--limit 150] [FILE ...]

A small brace matcher, not a C parser: comments, string and character literals and
preprocessor lines are blanked first (so braces in them do not count), then every ``{`` at file
level whose previous token is ``)`` opens a function body (initialisers follow ``=``, struct and
enum bodies a name or keyword). tests/mkv_env/test_c_layout.py runs ``check``.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LIMIT = 150
FILE_LIMIT = 1000


def source_files(root: Path = ROOT) -> list[Path]:
    """mkv_env/_fastsim.c and every .c/.h file of mkv_env/_native, sorted."""
    native = root / "mkv_env" / "_native"
    files = sorted(p for p in native.glob("*") if p.suffix in (".c", ".h"))
    return [root / "mkv_env" / "_fastsim.c", *files]


def blank_noncode(text: str) -> str:
    """``text`` with comments, string/char literals and preprocessor lines replaced by spaces
    (newlines kept, so line numbers stay)."""
    out = []
    i, n = 0, len(text)
    line_start = True
    while i < n:
        c = text[i]
        if line_start and c in " \t":
            out.append(c)
            i += 1
            continue
        if line_start and c == "#":  # a directive, with its backslash continuations
            while i < n and text[i] != "\n":
                if text[i] == "\\" and i + 1 < n and text[i + 1] == "\n":
                    out.append(" \n")
                    i += 2
                    continue
                out.append(" ")
                i += 1
            continue
        line_start = False
        if text.startswith("//", i):
            while i < n and text[i] != "\n":
                out.append(" ")
                i += 1
        elif text.startswith("/*", i):
            end = text.find("*/", i + 2)
            end = n if end < 0 else end + 2
            out.append(re.sub(r"[^\n]", " ", text[i:end]))
            i = end
        elif c in "\"'":
            j = i + 1
            while j < n and text[j] != c and text[j] != "\n":
                j += 2 if text[j] == "\\" else 1
            j = min(j + 1, n)
            out.append(re.sub(r"[^\n]", " ", text[i:j]))
            i = j
        else:
            if c == "\n":
                line_start = True
            out.append(c)
            i += 1
    return "".join(out)


def functions(path: Path) -> list[tuple[str, int, int]]:
    """(name, first line, length in lines) of each function defined in the file ``path``."""
    code = blank_noncode(path.read_text())
    found = []
    depth = 0
    i = 0
    while i < len(code):
        c = code[i]
        if c == "{":
            if depth == 0:
                k = len(code[:i].rstrip())
                if k > 0 and code[k - 1] == ")":
                    start_paren = _matching_open(code, k - 1)
                    m = re.search(r"([A-Za-z_]\w*)\s*$", code[:start_paren])
                    end = _matching_close(code, i)
                    if m is not None and end is not None:
                        first = code.count("\n", 0, m.start(1)) + 1
                        last = code.count("\n", 0, end) + 1
                        found.append((m.group(1), first, last - first + 1))
                        i = end + 1
                        continue
            depth += 1
        elif c == "}":
            depth -= 1
        i += 1
    return found


def _matching_open(code: str, close: int) -> int:
    depth = 0
    for j in range(close, -1, -1):
        if code[j] == ")":
            depth += 1
        elif code[j] == "(":
            depth -= 1
            if depth == 0:
                return j
    return 0


def _matching_close(code: str, open_: int) -> int | None:
    depth = 0
    for j in range(open_, len(code)):
        if code[j] == "{":
            depth += 1
        elif code[j] == "}":
            depth -= 1
            if depth == 0:
                return j
    return None


def check(files: list[Path] | None = None, limit: int = LIMIT):
    """(every function as (path, name, first line, length), longest first; those >= limit)."""
    rows = [(p, name, first, length)
            for p in (files if files is not None else source_files())
            for name, first, length in functions(p)]
    rows.sort(key=lambda r: (-r[3], str(r[0]), r[2]))
    return rows, [r for r in rows if r[3] >= limit]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path)
    ap.add_argument("--limit", type=int, default=LIMIT)
    args = ap.parse_args(argv)
    rows, bad = check(args.files or None, args.limit)
    try:
        for p, name, first, length in rows:
            rel = p.resolve().relative_to(ROOT) if p.resolve().is_relative_to(ROOT) else p
            print(f"{length:5d}  {name}  ({rel}:{first})")
        sys.stdout.flush()
    except BrokenPipeError:  # (piped into head)
        sys.stdout = None
    if bad:
        print(f"{len(bad)} function(s) of {args.limit} lines or more", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
