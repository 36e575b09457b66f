"""The compiled kernel's C stays in small pieces: each file of mkv_env/_native under 1,000 lines,
each function of it and of mkv_env/_fastsim.c under 150 (scripts/c_function_lengths.py); every
Python function of mkv_env under 100."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _lengths_module():
    path = ROOT / "scripts" / "c_function_lengths.py"
    spec = importlib.util.spec_from_file_location("c_function_lengths", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_native_files_are_under_1000_lines():
    files = sorted((ROOT / "mkv_env" / "_native").glob("*.[ch]"))
    assert files, "mkv_env/_native holds no C files"
    long = {p.name: n for p in files if (n := len(p.read_text().splitlines())) >= 1000}
    assert not long, f"files of 1,000 lines or more: {long}"


def test_every_c_function_is_under_150_lines():
    mod = _lengths_module()
    rows, bad = mod.check()
    names = {name for _, name, _, _ in rows}
    assert {"advance_one", "step_slot", "reset_slot", "PyInit__fastsim"} <= names
    assert not bad, [(p.name, name, length) for p, name, _, length in bad]
    assert all(length < 150 for _, _, _, length in rows)


def test_the_counter_ignores_braces_in_strings_comments_and_directives(tmp_path):
    src = tmp_path / "t.c"
    src.write_text('static int f(void)\n{\n    const char *s = "}{\\"}";\n'
                   "    char c = '}'; /* } { */\n    // {\n#define OPEN {\n    return 0;\n}\n"
                   "static const int table[2] = {1, 2};\n"
                   "static int g(int a,\n             int b)\n{\n    if (a) {\n        return b;\n"
                   "    }\n    return a;\n}\n")
    assert _lengths_module().functions(src) == [("f", 1, 8), ("g", 10, 8)]


def test_every_python_function_of_mkv_env_is_under_100_lines():
    """The Python side kept as readable as the C side: no function of mkv_env over 100 lines
    (signature to last line, docstring included)."""
    import ast

    long = []
    for path in sorted((ROOT / "mkv_env").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines >= 100:
                    long.append(f"{path.name}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long
