"""The one adapter between mkv_env and pymunk's internals, checked at import.

The compiled kernel (``mkv_env._fastsim``) and the fast Python paths reach Chipmunk below
pymunk's public API: function addresses from pymunk's cffi module (``pymunk._chipmunk``), the
C objects behind ``Space``/``Body``/``Shape``, and pymunk wrappers built around C objects made
by the kernel (:func:`wrap_space`, :func:`wrap_body`, :func:`wrap_shape`, with copies of pymunk's
own finalisers). Every one of those touches is declared here, and :func:`problems` checks, at
import, that the installed pymunk still matches them:

- its version is in :data:`TESTED` (the pin in pyproject.toml);
- every Chipmunk function the code calls exists with the C signature in :data:`SIGNATURES` (the
  signatures the C code re-declares as function-pointer types);
- the structs the C code re-declares (:data:`STRUCTS`) have the same size and field offsets;
- the contact callbacks return ``void`` (pymunk's patched Chipmunk; Chipmunk 7's ``begin``
  returns a ``cpBool``), and the ``ext_*`` iterator callbacks pymunk's finalisers use exist;
- a new ``Space``/``Body`` has exactly the private attributes :func:`wrap_space`/
  :func:`wrap_body` set, and a shape the ``_init``/``_shape`` it needs.

Any mismatch turns the compiled kernel and the cffi paths off (:data:`fastsim`, :data:`cp`,
:data:`ffi` are then ``None``) with one warning line: everything then runs the Python reference
on pymunk's public API, which gives the same results, slower. Nothing reaches a private field of
a pymunk object that this check did not vouch for.

Moving the pin to a new pymunk: install it, run ``python -c "import mkv_env.chipmunk as c;
print(c.problems())"`` (it must print ``[]``; if a signature or attribute changed, change the C
declarations and the wrappers to match first), then ``pytest tests/mkv_env`` (the bit-for-bit
equivalence of the kernels and the fingerprints), then add the version to :data:`TESTED` and
widen ``pymunk`` in pyproject.toml.
"""

from __future__ import annotations

import gc
import warnings
import weakref

import pymunk

#: pymunk (major, minor) versions this adapter was tested against (pyproject.toml pins them).
TESTED = ((7, 3),)

#: Every Chipmunk function mkv_env calls below pymunk's API, with the C type it assumes
#: (cffi's spelling; the C code declares the same types as function pointers).
SIGNATURES = {
    "cpArbiterGetShapes": "void(*)(struct cpArbiter *, struct cpShape * *, struct cpShape * *)",
    "cpBodyEachConstraint":
        "void(*)(struct cpBody *, void(*)(struct cpBody *, struct cpConstraint *, void *), void *)",
    "cpBodyEachShape":
        "void(*)(struct cpBody *, void(*)(struct cpBody *, struct cpShape *, void *), void *)",
    "cpBodyFree": "void(*)(struct cpBody *)",
    "cpBodyGetAngle": "double(*)(struct cpBody *)",
    "cpBodyGetAngularVelocity": "double(*)(struct cpBody *)",
    "cpBodyGetPosition": "struct cpVect(*)(struct cpBody *)",
    "cpBodyGetSpace": "struct cpSpace *(*)(struct cpBody *)",
    "cpBodyGetVelocity": "struct cpVect(*)(struct cpBody *)",
    "cpBodyNew": "struct cpBody *(*)(double, double)",
    "cpBodyNewStatic": "struct cpBody *(*)()",
    "cpBodySetAngle": "void(*)(struct cpBody *, double)",
    "cpBodySetForce": "void(*)(struct cpBody *, struct cpVect)",
    "cpBodySetPosition": "void(*)(struct cpBody *, struct cpVect)",
    "cpBodySetTorque": "void(*)(struct cpBody *, double)",
    "cpBodySetUserData": "void(*)(struct cpBody *, void *)",
    "cpCircleShapeNew": "struct cpShape *(*)(struct cpBody *, double, struct cpVect)",
    "cpConstraintGetSpace": "struct cpSpace *(*)(struct cpConstraint *)",
    "cpPolyShapeNew":
        "struct cpShape *(*)(struct cpBody *, int, struct cpVect *, struct cpTransform, double)",
    "cpSegmentShapeNew":
        "struct cpShape *(*)(struct cpBody *, struct cpVect, struct cpVect, double)",
    "cpShapeFree": "void(*)(struct cpShape *)",
    "cpShapeGetBody": "struct cpBody *(*)(struct cpShape *)",
    "cpShapeGetCollisionType": "uintptr_t(*)(struct cpShape *)",
    "cpShapeGetSpace": "struct cpSpace *(*)(struct cpShape *)",
    "cpShapeSetBody": "void(*)(struct cpShape *, struct cpBody *)",
    "cpShapeSetCollisionType": "void(*)(struct cpShape *, uintptr_t)",
    "cpShapeSetElasticity": "void(*)(struct cpShape *, double)",
    "cpShapeSetFilter": "void(*)(struct cpShape *, struct cpShapeFilter)",
    "cpShapeSetFriction": "void(*)(struct cpShape *, double)",
    "cpShapeSetHashID": "void(*)(struct cpShape *, uintptr_t)",
    "cpSpaceAddBody": "struct cpBody *(*)(struct cpSpace *, struct cpBody *)",
    "cpSpaceAddCollisionHandler":
        "struct cpCollisionHandler *(*)(struct cpSpace *, uintptr_t, uintptr_t)",
    "cpSpaceAddShape": "struct cpShape *(*)(struct cpSpace *, struct cpShape *)",
    "cpSpaceEachBody": "void(*)(struct cpSpace *, void(*)(struct cpBody *, void *), void *)",
    "cpSpaceEachConstraint":
        "void(*)(struct cpSpace *, void(*)(struct cpConstraint *, void *), void *)",
    "cpSpaceEachShape": "void(*)(struct cpSpace *, void(*)(struct cpShape *, void *), void *)",
    "cpSpaceFree": "void(*)(struct cpSpace *)",
    "cpSpaceNew": "struct cpSpace *(*)()",
    "cpSpacePointQueryNearest": "struct cpShape *(*)(struct cpSpace *, struct cpVect, double, "
                                "struct cpShapeFilter, struct cpPointQueryInfo *)",
    "cpSpaceReindexShapesForBody": "void(*)(struct cpSpace *, struct cpBody *)",
    "cpSpaceRemoveBody": "void(*)(struct cpSpace *, struct cpBody *)",
    "cpSpaceRemoveConstraint": "void(*)(struct cpSpace *, struct cpConstraint *)",
    "cpSpaceRemoveShape": "void(*)(struct cpSpace *, struct cpShape *)",
    "cpSpaceSetDamping": "void(*)(struct cpSpace *, double)",
    "cpSpaceSetIterations": "void(*)(struct cpSpace *, int)",
    "cpSpaceShapeQuery": "unsigned char(*)(struct cpSpace *, struct cpShape *, void(*)(struct "
                         "cpShape *, struct cpContactPointSet *, void *), void *)",
    "cpSpaceStep": "void(*)(struct cpSpace *, double)",
    # the contact callbacks the kernel installs (C functions of _fastsim)
    "cpCollisionBeginFunc": "void(*)(struct cpArbiter *, struct cpSpace *, void *)",
    "cpCollisionSeparateFunc": "void(*)(struct cpArbiter *, struct cpSpace *, void *)",
    # pymunk's own iterator callbacks, which its finalisers (copied below) pass to Chipmunk
    "ext_cpSpaceShapeIteratorFunc": "void(*)(struct cpShape *, void *)",
    "ext_cpSpaceConstraintIteratorFunc": "void(*)(struct cpConstraint *, void *)",
    "ext_cpSpaceBodyIteratorFunc": "void(*)(struct cpBody *, void *)",
    "ext_cpBodyShapeIteratorFunc": "void(*)(struct cpBody *, struct cpShape *, void *)",
    "ext_cpBodyConstraintIteratorFunc": "void(*)(struct cpBody *, struct cpConstraint *, void *)",
}

#: Structs the C code re-declares: size and (field, offset) pairs it assumes (x86-64 / aarch64).
STRUCTS = {
    "cpVect": (16, (("x", 0), ("y", 8))),
    "cpShapeFilter": (16, (("group", 0), ("categories", 8), ("mask", 12))),
    "cpPointQueryInfo": (48, (("shape", 0), ("point", 8), ("distance", 24), ("gradient", 32))),
    "cpTransform": (48, (("a", 0), ("b", 8), ("c", 16), ("d", 24), ("tx", 32), ("ty", 40))),
}

#: The private attributes a new ``pymunk.Space()`` / ``pymunk.Body()`` has: what
#: :func:`wrap_space` / :func:`wrap_body` set on wrappers of objects made in C.
SPACE_ATTRS = frozenset({
    "_add_later", "_bodies", "_bodies_to_check", "_constraints", "_handlers", "_locked",
    "_post_step_callbacks", "_remove_later", "_removed_shapes", "_shapes", "_space",
    "_static_body", "threaded"})
BODY_ATTRS = frozenset({"_body", "_constraints", "_data_handle", "_shapes", "_space"})


class ChipmunkMismatchWarning(UserWarning):
    """The installed pymunk differs from what the compiled kernel was built against."""


def _typename(ffi, lib, name: str) -> str | None:
    if name in ("cpCollisionBeginFunc", "cpCollisionSeparateFunc"):
        return ffi.typeof(name).cname
    fn = getattr(lib, name, None)
    return None if fn is None else ffi.typeof(fn).cname


def problems(version: str | None = None, ffi=None, lib=None, signatures=None, structs=None,
             tested=None) -> list[str]:
    """What differs between the installed pymunk and what mkv_env assumes (empty: nothing).
    Every argument defaults to the installed pymunk / this module's tables (tests pass others)."""
    version = pymunk.version if version is None else version
    signatures = SIGNATURES if signatures is None else signatures
    structs = STRUCTS if structs is None else structs
    tested = TESTED if tested is None else tested
    found = []
    try:
        major_minor = tuple(int(p) for p in str(version).split(".")[:2])
    except ValueError:
        major_minor = ()
    if major_minor not in tested:
        found.append(f"pymunk {version} is not a tested version "
                     f"({', '.join(f'{a}.{b}.x' for a, b in tested)})")
    if ffi is None or lib is None:
        try:
            from pymunk._chipmunk import ffi as ffi_
            from pymunk._chipmunk import lib as lib_
        except ImportError:
            return [*found, "pymunk has no cffi module pymunk._chipmunk"]
        ffi, lib = ffi if ffi is not None else ffi_, lib if lib is not None else lib_
    for name, want in signatures.items():
        try:
            got = _typename(ffi, lib, name)
        except Exception:  # noqa: BLE001 - cffi raises several kinds for an unknown name
            got = None
        if got != want:
            found.append(f"Chipmunk's {name} is {got or 'missing'}, not {want}")
    for name, (size, fields) in structs.items():
        try:
            got = (ffi.sizeof(name), tuple((f, ffi.offsetof(name, f)) for f, _ in fields))
        except Exception:  # noqa: BLE001
            got = None
        if got != (size, fields):
            found.append(f"Chipmunk's struct {name} has layout {got}, not {(size, fields)}")
    found += _attribute_problems()
    return found


def _attribute_problems() -> list[str]:
    found = []
    space, body = pymunk.Space(), pymunk.Body(1.0, 1.0)
    shape = pymunk.Circle(body, 1.0)
    if set(vars(space)) != SPACE_ATTRS:
        found.append(f"pymunk.Space's attributes changed: {sorted(set(vars(space)) ^ SPACE_ATTRS)}")
    if set(vars(body)) != BODY_ATTRS:
        found.append(f"pymunk.Body's attributes changed: {sorted(set(vars(body)) ^ BODY_ATTRS)}")
    if not (callable(getattr(shape, "_init", None)) and hasattr(shape, "_shape")):
        found.append("pymunk shapes lost _init/_shape")
    return found


def _load():
    try:
        from pymunk._chipmunk import ffi as ffi_
        from pymunk._chipmunk import lib as lib_
    except ImportError:  # pragma: no cover - a pymunk build without cffi
        return None, None, None, []
    try:
        from mkv_env import _fastsim as fast
    except ImportError:  # pragma: no cover - installed without a C compiler
        fast = None
    found = problems(ffi=ffi_, lib=lib_)
    if found:
        more = (f" (and {len(found) - 1} more: mkv_env.chipmunk.problems())"
                if len(found) > 1 else "")
        warnings.warn_explicit(
            f"{found[0]}{more}; mkv_env runs its Python reference on pymunk's public API "
            "(same results, slower) instead of the compiled kernel",
            ChipmunkMismatchWarning, "mkv_env", 0)
        return None, None, None, found
    return ffi_, lib_, fast, found


#: pymunk's cffi module and library, and the compiled kernel: ``None`` when not there or when
#: :data:`PROBLEMS` is not empty.
ffi, cp, fastsim, PROBLEMS = _load()
COMPATIBLE = not PROBLEMS


# ---------------------------------------------------------------- the C objects behind pymunk's
def address(obj) -> int:
    """The address of the Chipmunk object behind a pymunk Space, Body or Shape."""
    return int(ffi.cast("uintptr_t", c_object(obj)))


def c_object(obj):
    """The cffi pointer behind a pymunk Space, Body or Shape (for calls through :data:`cp`)."""
    if isinstance(obj, pymunk.Space):
        return obj._space
    return obj._body if isinstance(obj, pymunk.Body) else obj._shape


def pending(space) -> bool:
    """Does pymunk hold bodies whose shapes it has yet to reindex (its next step does it)?"""
    return bool(space._bodies_to_check)


def shapes_table(space) -> dict:
    """pymunk's own shape table of ``space`` (an insertion-ordered dict used as a set)."""
    return space._shapes


def addresses(*names) -> list[int]:
    """The addresses of Chipmunk functions, for the compiled kernel's ``bind*`` calls."""
    return [int(ffi.cast("uintptr_t", ffi.addressof(cp, name))) for name in names]


# ---------------------------------------------------------------- wrappers of objects made in C
def _collect(each, owner, func) -> list:
    """Every object ``each(owner, func, handle)`` reports, robust to a Ctrl-C: Python raises a
    pending ``KeyboardInterrupt`` at the first bytecode it runs, which can be inside pymunk's
    iterator callback, where cffi prints and drops it and the object is not reported. Freeing
    the space then would leave that object pointing into freed memory (a crash later, found
    with a Ctrl-C during a reset: tests/sfm_learn/cli/test_interrupts.py). So the caller removes
    what one pass reports and asks again, until two passes in a row report nothing."""
    found: list = []
    h = ffi.new_handle(found)
    each(owner, func, h)
    return found


def _drain(each, owner, func, remove) -> None:
    """``remove`` every object ``each`` reports of ``owner``, asking again until two passes in a
    row report nothing (:func:`_collect`: a pass can miss one)."""
    empty = 0
    while empty < 2:
        objs = _collect(each, owner, func)
        empty = 0 if objs else empty + 1
        for obj in objs:
            remove(obj)


def _no_gc(free):
    """``free`` with the cyclic collector off while it runs: the iterations lock the space, and a
    collection run from inside their callbacks (an allocation) would free other objects of the
    same space there, which Chipmunk aborts on ("This operation cannot be done safely during a
    call to cpSpaceStep() or during a query")."""

    def run(cp_obj) -> None:
        was = gc.isenabled()
        gc.disable()
        try:
            free(cp_obj)
        finally:
            if was:
                gc.enable()

    run.__doc__ = free.__doc__
    return run


@_no_gc
def _free_space(cp_space) -> None:
    """pymunk.Space's own finaliser (``spacefree`` in pymunk/space.py), for a space made in C;
    each kind of object removed in passes until two in a row find none (:func:`_collect`)."""
    lib = cp

    def remove_shape(cp_shape):
        lib.cpSpaceRemoveShape(lib.cpShapeGetSpace(cp_shape), cp_shape)
        lib.cpShapeSetBody(cp_shape, ffi.NULL)

    _drain(lib.cpSpaceEachShape, cp_space, lib.ext_cpSpaceShapeIteratorFunc, remove_shape)
    _drain(lib.cpSpaceEachConstraint, cp_space, lib.ext_cpSpaceConstraintIteratorFunc,
          lambda c: lib.cpSpaceRemoveConstraint(lib.cpConstraintGetSpace(c), c))
    _drain(lib.cpSpaceEachBody, cp_space, lib.ext_cpSpaceBodyIteratorFunc,
          lambda b: lib.cpSpaceRemoveBody(lib.cpBodyGetSpace(b), b))
    lib.cpSpaceFree(cp_space)


@_no_gc
def _free_body(cp_body) -> None:
    """pymunk.Body's own finaliser (``freebody`` in pymunk/body.py), for a body made in C. Its
    iterator callbacks detach each shape and constraint; a Ctrl-C dropped inside one skips it
    (:func:`_collect`), and detaching is idempotent, so each iteration runs twice."""
    lib = cp
    for _ in range(2):
        lib.cpBodyEachShape(cp_body, lib.ext_cpBodyShapeIteratorFunc, ffi.NULL)
        lib.cpBodyEachConstraint(cp_body, lib.ext_cpBodyConstraintIteratorFunc, ffi.NULL)
    cp_space = lib.cpBodyGetSpace(cp_body)
    if cp_space != ffi.NULL:
        lib.cpSpaceRemoveBody(cp_space, cp_body)
    lib.cpBodyFree(cp_body)


def wrap_space(address_: int):
    """A ``pymunk.Space`` for a cpSpace made in C (it owns and frees it from now on), with the
    attributes ``pymunk.Space()`` sets up (:data:`SPACE_ATTRS`, checked at import)."""
    space = pymunk.Space.__new__(pymunk.Space)
    space.threaded = False
    space._space = ffi.gc(ffi.cast("cpSpace *", address_), _free_space)
    space._handlers = {}
    space._post_step_callbacks = {}
    space._removed_shapes = {}
    space._shapes = {}
    space._bodies = {}
    space._static_body = None
    space._constraints = {}
    space._locked = False
    space._add_later = set()
    space._remove_later = {}
    space._bodies_to_check = set()
    return space


def wrap_body(address_: int, space, static: bool = False):
    """A ``pymunk.Body`` for a cpBody made in C and already in ``space``'s cpSpace (it owns and
    frees it from now on): ``space.static_body`` when ``static``, else one of ``space.bodies``."""
    body = pymunk.Body.__new__(pymunk.Body)
    body._body = ffi.gc(ffi.cast("cpBody *", address_), _free_body)
    body._space = weakref.ref(space)
    body._constraints = weakref.WeakKeyDictionary()
    body._shapes = {}
    body._data_handle = ffi.new_handle(body)
    cp.cpBodySetUserData(body._body, body._data_handle)
    if static:
        space._static_body = body
    else:
        space._bodies[body] = None
    return body


def wrap_shape(cls, address_: int, body, space):
    """A pymunk shape of class ``cls`` for a cpShape made in C and already in ``space`` (it owns
    and frees it from now on), set up by pymunk's own ``_init``."""
    shape = cls.__new__(cls)
    shape._init(body, ffi.cast("cpShape *", address_))
    shape._space = weakref.ref(space)
    space._shapes[shape] = None
    return shape
