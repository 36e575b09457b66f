"""The architecture as a test: imports only go down the layers, and there are no import cycles.

Layers, lowest first (docs/design.md section 8)::

    sfm_common                         helpers shared by everything
    mkv_env | calib                    the robot side and the calibration side (never each other)
    sfm_learn (package __init__)       registers policy specs
    sfm_learn.eigenspace -> evaluation -> baselines -> reporting -> cli

Inside calib, lowest first::

    calib.data -> estimators -> verdict -> routes -> simulation -> calib (the public API) -> cli

Every ``import``/``from ... import`` of a module is read with ``ast``, the ones inside functions
too (a lazy import is still a dependency), so a function-level import cannot hide an upward
dependency or a cycle.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("sfm_common", "mkv_env", "calib", "sfm_learn")

# (layer name, rank); a module may import modules of its own layer or of lower ranks only.
LAYERS = {
    "sfm_common": 0,
    "mkv_env": 1,
    "calib.data": 1.0,
    "calib.estimators": 1.1,
    "calib.verdict": 1.2,
    "calib.routes": 1.3,
    "calib.simulation": 1.4,
    "calib": 1.5,
    "calib.cli": 1.6,
    "sfm_learn": 2,
    "sfm_learn.eigenspace": 3,
    "sfm_learn.evaluation": 4,
    "sfm_learn.baselines": 5,
    "sfm_learn.reporting": 6,
    "sfm_learn.experiments": 7,
    "sfm_learn.cli": 8,
}
# Independent packages: neither may import the other, whatever their ranks.
SIBLINGS = {frozenset({"mkv_env", "calib"})}


def module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer_of(module: str) -> str | None:
    best = None
    for layer in LAYERS:
        if module == layer or module.startswith(layer + "."):
            if best is None or len(layer) > len(best):
                best = layer
    return best


def imports_of(path: pathlib.Path, module: str) -> set[str]:
    """Absolute names of the project modules ``path`` imports (relative imports resolved)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            # "from pkg import sub" may name a submodule: keep both candidates
            names = [prefix] + [f"{prefix}.{a.name}" for a in node.names]
        else:
            continue
        out.update(n for n in names if n.split(".")[0] in PACKAGES)
    return out


def project_modules() -> dict[str, pathlib.Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            mods[module_name(path)] = path
    return mods


MODULES = project_modules()


def resolve(name: str) -> str | None:
    """The project module ``name`` refers to (a name inside a module maps to the module)."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def graph() -> dict[str, set[str]]:
    g = {}
    for mod, path in MODULES.items():
        deps = {resolve(n) for n in imports_of(path, mod)}
        g[mod] = {d for d in deps if d is not None and d != mod}
    return g


def siblings(a: str, b: str) -> bool:
    return frozenset({a.split(".")[0], b.split(".")[0]}) in SIBLINGS


def test_the_layers_cover_every_module():
    assert all(layer_of(m) is not None for m in MODULES), "a module outside every layer"
    assert "sfm_learn.cli.app" in MODULES and "sfm_learn.eigenspace.policy" in MODULES
    assert "calib.estimators.forward.fit" in MODULES and "calib.verdict.reliability" in MODULES
    # every calib module sits in a sub-layer (the package __init__ and the cli aside)
    loose = [m for m in MODULES if m.startswith("calib.") and layer_of(m) == "calib"]
    assert not loose, f"calib modules outside calib's layers: {loose}"


def test_no_module_imports_a_layer_above_it_or_a_sibling():
    bad = []
    for mod, deps in graph().items():
        mine = layer_of(mod)
        for dep in deps:
            theirs = layer_of(dep)
            if LAYERS[theirs] > LAYERS[mine] or siblings(mine, theirs):
                bad.append(f"{mod} ({mine}) imports {dep} ({theirs})")
    assert not bad, "\n".join(sorted(bad))


def strongly_connected(g: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(g.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


# A package __init__ that re-exports its submodules and a submodule importing a sibling through
# the package are one cycle in the graph but harmless; only cycles between plain modules count.
def test_no_import_cycles():
    g = graph()
    plain = {m: {d for d in deps if not MODULES[d].name == "__init__.py"}
             for m, deps in g.items() if MODULES[m].name != "__init__.py"}
    cycles = strongly_connected(plain)
    assert not cycles, f"import cycles: {cycles}"


@pytest.mark.parametrize("bad", [
    ("sfm_learn.eigenspace.policy", "sfm_learn.cli.common"),
    ("mkv_env.envs", "sfm_learn.evaluation.runner"),
    ("calib.data.io", "mkv_env.files"),
])
def test_the_check_catches_an_upward_import(bad):
    """The rule fires on an upward or sideways import (guards the test itself)."""
    mod, dep = bad
    mine, theirs = layer_of(mod), layer_of(resolve(dep) or dep)
    assert LAYERS[theirs] > LAYERS[mine] or siblings(mine, theirs)


def test_cycle_detection_finds_a_cycle():
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [
        ["a", "b", "c"]]
