"""The repository carries what it cites: no file points at a tracker number or at a document
outside the project (the architecture notes the code cites live in docs/design.md)."""

from __future__ import annotations

import pathlib
import re
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUTSIDE = re.compile(r"\bissues? #?\d+\b|(?<![\w/])DESIGN\.md|\.\./shared\b"
                     r"|\bshared/(paper|data)\b", re.IGNORECASE)
SUFFIXES = {".py", ".c", ".h", ".md", ".yml", ".yaml", ".toml", ".cfg", ".txt", ""}


def _tracked() -> list[pathlib.Path]:
    try:
        out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                             timeout=60, check=True).stdout.split()
    except (OSError, subprocess.SubprocessError):
        pytest.skip("not a git checkout")
    return [ROOT / f for f in out if (ROOT / f).suffix in SUFFIXES and (ROOT / f).is_file()]


def test_no_file_cites_a_tracker_number_or_an_outside_document():
    me = pathlib.Path(__file__).resolve()
    found = []
    for path in _tracked():
        if path.resolve() == me or path.stat().st_size > 2_000_000:
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:90]}")
    assert not found, "\n".join(found)


def test_the_pattern_catches_what_it_is_for():
    for bad in ("see issue 26", "(issues 3)", "DESIGN.md section 4", "../shared/paper/x.txt",
                "`shared/data/`"):
        assert OUTSIDE.search(bad), bad
    for good in ("docs/design.md section 4", "the issue is", "tissue 3"):
        assert not OUTSIDE.search(good), good
