"""The adapter to pymunk's internals (mkv_env.chipmunk): its import-time check passes on the
installed pymunk, names every kind of mismatch, and a mismatch turns the compiled kernel off with
one warning line while the envs keep giving the same results on the Python reference."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from mkv_env import chipmunk


def test_the_installed_pymunk_matches_and_the_kernel_is_on():
    assert chipmunk.problems() == []
    assert chipmunk.COMPATIBLE and chipmunk.fastsim is not None and chipmunk.cp is not None


def test_every_chipmunk_call_of_the_package_is_declared():
    """Every ``cp*`` function the package binds or calls through the cffi lib is in SIGNATURES:
    nothing reaches Chipmunk past the check."""
    import pathlib
    import re

    root = pathlib.Path(chipmunk.__file__).parent
    used = set()
    for path in root.glob("*.py"):
        text = path.read_text()
        used |= set(re.findall(r"\b(?:_cp|lib|cp)\.(cp[A-Z]\w+)", text))
        for block in re.findall(r"addresses\(((?:\s*\"cp\w+\",?)+)", text):
            used |= set(re.findall(r"\"(cp\w+)\"", block))
    assert used, "the scan found no call: the pattern is broken"
    assert used <= set(chipmunk.SIGNATURES), sorted(used - set(chipmunk.SIGNATURES))


@pytest.mark.parametrize("change, needle", [
    ({"version": "7.9.0"}, "pymunk 7.9.0 is not a tested version"),
    ({"version": "8.0.0"}, "pymunk 8.0.0 is not a tested version"),
    ({"version": "garbage"}, "pymunk garbage is not a tested version"),
    ({"signatures": {**chipmunk.SIGNATURES, "cpBodyGetAngle": "float(*)(struct cpBody *)"}},
     "cpBodyGetAngle is double(*)(struct cpBody *), not float"),
    ({"signatures": {**chipmunk.SIGNATURES, "cpSpaceStepTwice": "void(*)(struct cpSpace *)"}},
     "cpSpaceStepTwice is missing"),
    ({"signatures": {**chipmunk.SIGNATURES,
                     "cpCollisionBeginFunc": "unsigned char(*)(struct cpArbiter *, "
                                             "struct cpSpace *, void *)"}},
     "cpCollisionBeginFunc is void"),
    ({"structs": {**chipmunk.STRUCTS, "cpVect": (24, (("x", 0), ("y", 8)))}},
     "struct cpVect has layout (16"),
    ({"structs": {**chipmunk.STRUCTS,
                  "cpShapeFilter": (16, (("group", 0), ("mask", 8), ("categories", 12)))}},
     "struct cpShapeFilter"),
])
def test_each_kind_of_mismatch_is_named_in_one_line(change, needle):
    found = chipmunk.problems(**change)
    assert len(found) == 1 and needle in found[0] and "\n" not in found[0], found


def test_a_changed_private_attribute_is_found(monkeypatch):
    import pymunk

    init = pymunk.Space.__init__

    def renamed(self, *a, **k):
        init(self, *a, **k)
        self._bodies_to_reindex = self.__dict__.pop("_bodies_to_check")

    monkeypatch.setattr(pymunk.Space, "__init__", renamed)
    found = chipmunk.problems()
    assert len(found) == 1 and "_bodies_to_check" in found[0] and "_bodies_to_reindex" in found[0]


_RUN = """
import json, sys, warnings
import pymunk
{patch}
import gymnasium as gym
import numpy as np
import mkv_env, mkv_env.kernel, mkv_env.robot
out = {{"kernel": bool(mkv_env.kernel.AVAILABLE), "default": mkv_env.robot.DEFAULT_KERNEL}}
for env_id in ("MKV-v1", "MKVJam-v1"):
    env = gym.make(env_id, kernel={kernel!r})
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    trace = [obs.tolist()]
    for _ in range(60):
        obs, r, term, trunc, info = env.step(rng.integers(0, 3, 2))
        trace.append([*obs.tolist(), float(r), bool(term)])
        if term or trunc:
            obs, _ = env.reset()
    out[env_id] = trace
    env.close()
vec = gym.make_vec("MKV-v1", num_envs=2, vectorization_mode="vector_entry_point")
o, _ = vec.reset(seed=5)
o2 = vec.step(np.ones((2, 2), dtype=np.int64))[0]
out["vec"] = [o.tolist(), o2.tolist()]
vec.close()
print(json.dumps(out))
"""


def _run(patch: str, kernel: str):
    r = subprocess.run([sys.executable, "-c", _RUN.format(patch=patch, kernel=kernel)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout), r.stderr


def test_a_mismatch_turns_the_kernel_off_with_one_line_and_the_same_results():
    """A pymunk reporting an untested version (as a new release would): one warning line, the
    compiled kernel and the cffi paths off, the envs on pymunk's public API give the very same
    observations, rewards and flags as the compiled kernel in a normal process."""
    off, err = _run('pymunk.version = "7.9.0"', "python")
    assert not off["kernel"] and off["default"] == "python", off
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "ChipmunkMismatchWarning" in lines[0], err
    assert "pymunk 7.9.0 is not a tested version" in lines[0] and "Python reference" in lines[0]
    on, err_on = _run("", "c")
    assert on["kernel"] and on["default"] == "c" and not err_on.strip(), err_on
    for key in ("MKV-v1", "MKVJam-v1", "vec"):
        assert off[key] == on[key], key


def test_asking_for_the_c_kernel_after_a_mismatch_is_one_clear_line():
    code = ('import pymunk; pymunk.version = "7.9.0"\n'
            "import warnings; warnings.simplefilter('ignore')\n"
            "import gymnasium as gym, mkv_env\n"
            "try:\n    gym.make('MKV-v1', kernel='c')\n"
            "except Exception as e:\n    print(type(e).__name__, str(e).count(chr(10)), e)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    kind, newlines, *_ = r.stdout.split(" ", 2)
    assert kind == "ValueError" and newlines == "0", r.stdout
    assert "kernel='c' is off: pymunk 7.9.0 is not a tested version" in r.stdout, r.stdout


def test_a_pass_that_misses_an_object_is_repeated_until_none_is_left():
    """A Ctrl-C raised inside pymunk's iterator callback is printed and dropped by cffi, and
    the object it was reporting is missed (found in CI: a Ctrl-C during a reset crashed
    ``mkv record``). The finaliser's removal asks again until two passes report nothing."""
    live = {1, 2, 3, 4, 5}
    passes = []

    def each(owner, func, handle):  # one missed object on the first pass, as a dropped Ctrl-C
        found = chipmunk.ffi.from_handle(handle)
        objs = sorted(live)
        found.extend(objs[1:] if not passes else objs)
        passes.append(len(objs))

    chipmunk._drain(each, None, None, live.discard)
    assert live == set() and passes == [5, 1, 0, 0]


def test_the_finalisers_run_without_the_cyclic_collector():
    """A collection from inside an iteration callback would free other objects of the locked
    space (Chipmunk aborts); the finalisers switch it off and restore it, even on an error."""
    import gc

    seen = []

    @chipmunk._no_gc
    def free(x):
        seen.append(gc.isenabled())
        if x:
            raise KeyboardInterrupt

    assert gc.isenabled()
    free(0)
    with pytest.raises(KeyboardInterrupt):
        free(1)
    assert seen == [False, False] and gc.isenabled()
    gc.disable()
    try:
        free(0)
        assert not gc.isenabled()  # left as it was
    finally:
        gc.enable()
