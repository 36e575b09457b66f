"""calib's design record and its code agree, and calib stays in files a reader can hold.

- Every module-level constant of calib (a tunable threshold, a budget, a fixed choice) is named
  once, in one module, beside the decision of docs/calib_design.md it rests on: its ``#:``
  comment cites ``docs/calib_design.md D<n>``, and the record's Thresholds table lists it with
  the same module and decision.
- No calib file is over 800 lines.
"""

from __future__ import annotations

import ast
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[2]
CALIB = ROOT / "calib"
RECORD = ROOT / "docs" / "calib_design.md"
CONSTANT = re.compile(r"^_?[A-Z][A-Z0-9_]*$")
ROW = re.compile(r"^\|\s*`(?P<name>[A-Za-z_0-9]+)`\s*\|(?P<value>[^|]*)\|\s*(?P<module>[^|]+?)\s*\|"
                 r"\s*(?P<decision>D\d+)\s*\|\s*$")
CITE = re.compile(r"docs/calib_design\.md,? (D\d+)")
MAX_LINES = 800


def constants() -> dict[str, list[tuple[str, int]]]:
    """name -> [(module path relative to the repository, line)] over every calib module."""
    out: dict[str, list[tuple[str, int]]] = {}
    for path in sorted(CALIB.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in tree.body:
            targets = (node.targets if isinstance(node, ast.Assign)
                       else [node.target] if isinstance(node, ast.AnnAssign) else [])
            for t in targets:
                if isinstance(t, ast.Name) and CONSTANT.match(t.id) and t.id != "__all__":
                    out.setdefault(t.id, []).append(
                        (path.relative_to(ROOT).as_posix(), node.lineno))
    return out


def table() -> dict[str, tuple[str, str]]:
    text = RECORD.read_text(encoding="utf-8")
    rows = {}
    for line in text.split("## Thresholds", 1)[1].splitlines():
        m = ROW.match(line)
        if m:
            assert m["name"] not in rows, f"{m['name']} listed twice in the Thresholds table"
            rows[m["name"]] = (m["module"].strip("` "), m["decision"])
    return rows


def decisions() -> set[str]:
    return set(re.findall(r"^### (D\d+)\. ", RECORD.read_text(encoding="utf-8"), re.M))


def comment_above(path: str, lineno: int) -> str:
    """The ``#:`` / ``#`` comment block just above line ``lineno`` of ``path``, and the line."""
    lines = (ROOT / path).read_text(encoding="utf-8").splitlines()
    i = lineno - 2
    block = [lines[lineno - 1]]
    while i >= 0 and lines[i].lstrip().startswith("#"):
        block.append(lines[i])
        i -= 1
    return "\n".join(reversed(block))


def test_every_constant_is_defined_once():
    twice = {k: v for k, v in constants().items() if len(v) > 1}
    assert not twice, f"constants defined in more than one place: {twice}"


def test_the_thresholds_table_lists_every_constant_where_it_is():
    code, rows = constants(), table()
    assert set(code) - set(rows) == set(), "constants missing from docs/calib_design.md"
    assert set(rows) - set(code) == set(), "the Thresholds table lists constants calib lacks"
    wrong = {k: (rows[k][0], v[0][0]) for k, v in code.items() if rows[k][0] != v[0][0]}
    assert not wrong, f"module in the table != module in the code: {wrong}"
    missing = {d for _, d in rows.values()} - decisions()
    assert not missing, f"the table cites decisions the record lacks: {missing}"


def test_every_constant_cites_its_decision():
    rows, bad = table(), []
    for name, [(path, lineno)] in constants().items():
        cited = CITE.findall(comment_above(path, lineno))
        if rows[name][1] not in cited:
            bad.append(f"{path}:{lineno} {name}: cites {cited}, the table says {rows[name][1]}")
    assert not bad, "\n".join(bad)


def test_no_calib_file_is_over_800_lines():
    long = {p.relative_to(ROOT).as_posix(): n for p in CALIB.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert not long, long


def test_the_checks_read_what_they_are_for():
    """The parsers of this file find what they look for (guards the checks themselves)."""
    assert ROW.match("| `GRID` | 2000 | calib/estimators/forward/problem.py | D36 |")
    assert not ROW.match("| constant | value | module | decision |")
    assert CITE.findall("#: 5 degrees apart (docs/calib_design.md D36).") == ["D36"]
    assert "GRID" in constants() and len(table()) >= 80 and "D1" in decisions()


def test_the_user_guide_is_a_guide():
    """docs/calib.md stays a guide a newcomer reads through (at most 500 lines); the reasons go
    to docs/calib_design.md and the study tables to docs/calib_study.md."""
    guide = (ROOT / "docs" / "calib.md").read_text(encoding="utf-8")
    assert len(guide.splitlines()) <= 500
    for page in ("calib_design.md", "calib_study.md"):
        assert page in guide and (ROOT / "docs" / page).is_file()
