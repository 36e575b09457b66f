"""The vectors the compiled kernel and Python share, built and read by name.

The C side declares each layout once, as an X-macro list in ``mkv_env/_native/kernel.h``, from
which both its enum and the extension's ``LAYOUTS`` table are generated:
``{"K": ((name, offset, width), ...), ...}`` for the robot constants (K), the wheel state (S),
a batch's parameters (P), a slot's other doubles (V, after S), the output buffers (O, with their
buffer format), the arena layout constants (L) and the reset constants (R). Python never
indexes these vectors by position: :func:`pack` takes a dict of every field by name and
:func:`unpack` gives one back, and both refuse a name set that differs from the C side's, so a
field added, removed or moved on one side cannot silently shift the other.
"""

from __future__ import annotations

import array
from collections.abc import Mapping, Sequence

from mkv_env.chipmunk import fastsim as _fastsim

#: The extension's layouts (empty without the compiled kernel).
LAYOUTS: dict = dict(getattr(_fastsim, "LAYOUTS", {}) or {})


class LayoutMismatch(ValueError):
    """Python and the compiled kernel disagree on a vector's fields (a stale build?)."""


def fields(kind: str) -> tuple:
    """``((name, offset, width), ...)`` of layout ``kind`` ("K", "S", "P", "V", "O", "L", "R")."""
    try:
        return LAYOUTS[kind]
    except KeyError:
        raise LayoutMismatch(f"the compiled kernel has no layout {kind!r} "
                             f"(it has {sorted(LAYOUTS)}): rebuild it") from None


def names(kind: str) -> tuple[str, ...]:
    """The field names of layout ``kind``, in the kernel's order."""
    return tuple(f[0] for f in fields(kind))


def length(kind: str) -> int:
    """The number of doubles (or buffers, for "O") of layout ``kind``."""
    return sum(f[2] for f in fields(kind))


def check_names(kind: str, given) -> None:
    """Raise :class:`LayoutMismatch` naming the fields only one side has."""
    want, got = set(names(kind)), set(given)
    if want != got:
        raise LayoutMismatch(
            f"layout {kind}: the compiled kernel has {sorted(want - got) or 'no other'} fields, "
            f"Python {sorted(got - want) or 'no other'}: the build is stale (rebuild mkv_env)")


def pack(kind: str, values: Mapping[str, float | Sequence[float]], start: int = 0) -> array.array:
    """The doubles of layout ``kind`` from ``values`` (a number per field of width 1, a sequence
    of ``width`` numbers otherwise). ``start``: the layout's first offset (V follows S)."""
    check_names(kind, values)
    out = array.array("d", bytes(8 * length(kind)))
    for name, offset, width, *_ in fields(kind):
        v = values[name]
        if width == 1:
            out[offset - start] = float(v)
            continue
        v = [float(x) for x in v]
        if len(v) != width:
            raise LayoutMismatch(f"layout {kind}: field {name} has {width} values in the "
                                 f"compiled kernel, {len(v)} in Python")
        out[offset - start:offset - start + width] = array.array("d", v)
    return out


def unpack(kind: str, vector: Sequence[float], start: int = 0) -> dict:
    """``{name: value (or list of width values)}`` of a vector of layout ``kind``."""
    out = {}
    for name, offset, width, *_ in fields(kind):
        i = offset - start
        out[name] = vector[i] if width == 1 else list(vector[i:i + width])
    return out
