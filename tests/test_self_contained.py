"""The repository carries what it cites and speaks of itself as it is: no file points at a
tracker number or at a document outside the project (the architecture notes the code cites live
in docs/design.md), and none names a step or a working session of the project's development
(numbered, or "this" and "that" one): history lives in git log, the reasons for the design in
docs/calib_design.md and docs/design.md."""

from __future__ import annotations

import pathlib
import re
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUTSIDE = re.compile(r"\bissues?[- ]#?\d+\b|(?<![\w/])DESIGN\.md|\.\./shared\b"
                     r"|\bshared/(paper|data)\b", re.IGNORECASE)
# A development step or working session named: a numbered one (also a range or hyphenated), or
# one pointed at ("this", "that", "earlier", "previous", ...); the forms are listed in
# test_the_pattern_catches_what_it_is_for.
HISTORY = re.compile(r"\bstops?[- ]\d+|\b(this|that|earlier|previous|next) stop\b"
                     r"|\b(this|that|earlier|previous|next|last) session\b"
                     r"|\bsessions? [1-9]\d*\b(?!\.\d)", re.IGNORECASE)
SUFFIXES = {".py", ".c", ".h", ".md", ".yml", ".yaml", ".toml", ".cfg", ".txt", ""}


def _tracked() -> list[pathlib.Path]:
    try:
        out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                             timeout=60, check=True).stdout.split()
    except (OSError, subprocess.SubprocessError):
        pytest.skip("not a git checkout")
    return [ROOT / f for f in out if (ROOT / f).suffix in SUFFIXES and (ROOT / f).is_file()]


def _lines_matching(pattern: re.Pattern) -> list[str]:
    me = pathlib.Path(__file__).resolve()
    found = []
    for path in _tracked():
        if path.resolve() == me or path.stat().st_size > 2_000_000:
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        # a phrase broken across two lines is caught too: each line is read with the next
        lines = text.splitlines()
        for n, line in enumerate(lines, 1):
            pair = line + " " + (lines[n].lstrip(" #*") if n < len(lines) else "")
            if pattern.search(line) or (pattern.search(pair)
                                        and not pattern.search(lines[n] if n < len(lines) else "")):
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:90]}")
    return found


def test_no_file_cites_a_tracker_number_or_an_outside_document():
    found = _lines_matching(OUTSIDE)
    assert not found, "\n".join(found)


def test_no_file_names_a_development_step():
    """Docs, README, comments, docstrings, test names and xfail reasons alike."""
    found = _lines_matching(HISTORY)
    assert not found, "\n".join(found)


def test_the_pattern_catches_what_it_is_for():
    for bad in ("see issue 26", "(issues 3)", "DESIGN.md section 4", "../shared/paper/x.txt",
                "`shared/data/`"):
        assert OUTSIDE.search(bad), bad
    for good in ("docs/design.md section 4", "the issue is", "tissue 3"):
        assert not OUTSIDE.search(good), good
    assert OUTSIDE.search("the issue-23 protocol")
    # the words are put together here so that this file does not match itself
    step = "st" + "op"
    for bad in (f"{step} 61", f"({step}s 55-56)", f"{step}-60's rule", f"until this {step}",
                f"{step} 66's CI", "tried in an earlier " + "session", "Session" + " 12"):
        assert HISTORY.search(bad), bad
    for good in (f"a non-{step} run", "scope=\"session\"", "a teleoperated session",
                 "its own session (setsid)", f"the robot comes to a {step}",
                 "a short session\n0.0  forward off"):
        assert not HISTORY.search(good), good
