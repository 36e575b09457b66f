"""The vectors C and Python share are built and read by name (mkv_env.layouts): the names come
from the C side's X-macro lists, and a field added, removed or moved on either side is a clear
one-line error, never a silent shift."""

from __future__ import annotations

import gymnasium as gym
import pytest

from mkv_env import kernel, layouts, robot
from mkv_env.params import RobotParams

pytestmark = pytest.mark.skipif(not layouts.LAYOUTS, reason="compiled kernel not built")


def test_every_layout_is_contiguous_and_its_length_is_the_kernels():
    lengths = {"K": "N_CONSTANTS", "P": "N_PARAMS", "R": "N_RESET"}
    for kind, fields in layouts.LAYOUTS.items():
        if kind == "O":  # buffers, one per entry (width: per slot)
            continue
        start = layouts.LAYOUTS["S"][-1][1] + 1 if kind == "V" else 0
        for name, offset, width, *_ in fields:
            assert offset == start and width >= 1, (kind, name)
            start += width
        if kind in lengths:
            assert start == getattr(kernel._fastsim, lengths[kind]), kind
    assert layouts.length("S") + layouts.length("V") == kernel._fastsim.N_VALUES
    assert [f[1] for f in layouts.LAYOUTS["O"]] == list(range(len(layouts.LAYOUTS["O"])))


def test_python_builds_every_vector_from_exactly_the_kernels_names():
    env = gym.make("MKV-v1")
    env.reset(seed=1)
    u = env.unwrapped
    built = {"K": robot.kernel_constants(u.robot_params), "P": kernel.params(u),
             "R": kernel.reset_constants(u), "L": kernel._layout_constants()}
    for kind, vec in built.items():
        assert len(vec) == layouts.length(kind), kind
        back = layouts.unpack(kind, vec)
        assert set(back) == set(layouts.names(kind))
    assert [o[0] for o in kernel.OUTPUTS][:2] == ["obs", "reward"]
    env.close()


def test_pack_and_unpack_round_trip_by_name():
    k = robot.kernel_constants(RobotParams())
    d = layouts.unpack("K", k)
    assert layouts.pack("K", d) == k
    assert d["MASS"] == RobotParams().mass_kg and d["MOMENT"] == k[-1]


@pytest.mark.parametrize("edit, needle", [
    (lambda f: (*f, ("NEW_FIELD", f[-1][1] + 1, 1)), "compiled kernel has ['NEW_FIELD']"),
    (lambda f: f[:-1], "Python ['MOMENT']"),
    (lambda f: tuple((n if n != "MASS" else "MASS_KG", o, w) for n, o, w in f),
     "['MASS_KG'] fields, Python ['MASS']"),
])
def test_a_field_changed_on_the_c_side_is_one_clear_line(monkeypatch, edit, needle):
    monkeypatch.setitem(layouts.LAYOUTS, "K", edit(layouts.LAYOUTS["K"]))
    with pytest.raises(layouts.LayoutMismatch) as e:
        robot.kernel_constants(RobotParams())
    msg = str(e.value)
    assert needle in msg and "\n" not in msg and "rebuild" in msg, msg


def test_a_width_changed_on_the_c_side_is_caught(monkeypatch):
    fields = tuple((n, o, 6 if n == "CDF" else w) for n, o, w in layouts.LAYOUTS["L"])
    monkeypatch.setitem(layouts.LAYOUTS, "L", fields)
    with pytest.raises(layouts.LayoutMismatch, match="field CDF has 6 values in the compiled"):
        kernel._layout_constants()


def test_an_output_buffer_changed_on_the_c_side_is_caught(monkeypatch):
    o = layouts.LAYOUTS["O"]
    monkeypatch.setitem(layouts.LAYOUTS, "O", tuple(
        (n, i, w, "d" if n == "JAMS" else f) for n, i, w, f in o))
    with pytest.raises(layouts.LayoutMismatch, match="output JAMS is 'd' x 1 in the compiled"):
        kernel._outputs()
    monkeypatch.setitem(layouts.LAYOUTS, "O", o[:-1])
    with pytest.raises(layouts.LayoutMismatch, match="Python \\['ESCAPED'\\]"):
        kernel._outputs()


def test_a_missing_layout_says_rebuild(monkeypatch):
    monkeypatch.delitem(layouts.LAYOUTS, "R")
    with pytest.raises(layouts.LayoutMismatch, match="no layout 'R'.*rebuild"):
        layouts.fields("R")
