"""The compiled extension's direct line to Chipmunk, for the worlds of the compiled step kernel.

Three things a kernel world (``World(..., fast_contacts=True)``) does without pymunk's Python
wrappers, each giving exactly what the wrappers give: contacts counted by C callbacks
(:func:`install_contacts`), obstacles built as raw Chipmunk shapes (:func:`add_static`, handed to
pymunk only when the world is pickled: :func:`adopt_static`), and the start-pose overlap query
(:func:`overlaps`). ``mkv_env._fastsim`` gets Chipmunk's function addresses from pymunk's cffi
module here, once.
"""

from __future__ import annotations

import array
import weakref

from mkv_env.robot import BUMP_FL, BUMP_FR, BUMP_REAR, CHASSIS, OBSTACLE, _cp, _fastsim, _ffi

#: True when the extension and pymunk's cffi layer are both there.
AVAILABLE = _fastsim is not None and _cp is not None and hasattr(_fastsim, "add_static")


def _addresses(*names) -> list[int]:
    return [int(_ffi.cast("uintptr_t", _ffi.addressof(_cp, name))) for name in names]


if AVAILABLE:
    _BEGIN, _SEPARATE = _fastsim.bind_kernel(*_addresses(
        "cpBodyGetPosition", "cpSpacePointQueryNearest", "cpArbiterGetShapes",
        "cpShapeGetCollisionType"))
    _fastsim.bind_shapes(*_addresses(
        "cpSegmentShapeNew", "cpPolyShapeNew", "cpCircleShapeNew", "cpShapeSetCollisionType",
        "cpShapeSetFriction", "cpShapeSetElasticity", "cpSpaceAddShape", "cpSpaceRemoveShape",
        "cpShapeGetSpace", "cpShapeFree", "cpShapeGetBody", "cpSpaceShapeQuery",
        "cpShapeSetHashID"))
    #: Resets in C (``Batch.set_reset``) build worlds with these, and set the contact handlers'
    #: fields at these offsets of Chipmunk's ``cpCollisionHandler``.
    RESET = hasattr(_fastsim, "bind_reset")
    if RESET:
        _fastsim.bind_reset(*_addresses(
            "cpSpaceNew", "cpSpaceFree", "cpSpaceSetIterations", "cpSpaceSetDamping", "cpBodyNew",
            "cpBodyNewStatic", "cpBodyFree", "cpSpaceAddBody", "cpSpaceRemoveBody",
            "cpBodySetPosition", "cpBodySetAngle", "cpShapeSetFilter",
            "cpSpaceReindexShapesForBody", "cpSpaceAddCollisionHandler"))
        HANDLER_OFFSETS = tuple(_ffi.offsetof("cpCollisionHandler", f)
                                for f in ("beginFunc", "separateFunc", "userData"))
else:  # pragma: no cover
    RESET = False


def install_contacts(world) -> None:
    """Count ``world``'s robot-obstacle contacts with the kernel's C callbacks: the same counts
    as :func:`mkv_env.world._on_begin`/``_on_separate``, in the same array ``world.contacts``,
    but Chipmunk never calls back into Python while stepping. The handlers are registered with
    Chipmunk directly; the counts array is kept by the pymunk space itself, because Chipmunk
    still calls "separate" while a dying space removes its shapes (the space's C object is freed
    before its other attributes). A pickled world gets all this again in World.__setstate__."""
    counts = world.contacts
    begin = _ffi.cast("cpCollisionBeginFunc", _BEGIN)
    separate = _ffi.cast("cpCollisionSeparateFunc", _SEPARATE)
    data = _ffi.cast("void *", counts.buffer_info()[0])
    space = world.space
    space._mkv_contact_counts = counts  # lives as long as the space (see above)
    for ctype in (CHASSIS, BUMP_FL, BUMP_FR, BUMP_REAR):
        h = _cp.cpSpaceAddCollisionHandler(space._space, ctype, OBSTACLE)
        h.beginFunc, h.separateFunc, h.userData = begin, separate, data


def add_static(world, wall_radius: float, friction: float, elasticity: float,
               first_hashid: int = -1):
    """``world.layout``'s obstacles as raw Chipmunk shapes on its space's static body, made as
    :func:`mkv_env.world.add_obstacles` makes them through pymunk (same shapes with the same
    radius, friction and elasticity, in the same order; ~10x faster). Returns the capsule that
    owns them (keep it as long as the world). Pymunk does not know these shapes: the world
    answers its own queries in C (:meth:`World.is_clear` through Chipmunk,
    :meth:`World.robot_overlaps` through :func:`overlaps`)."""
    space = world.space
    sb = space.static_body  # pymunk's own static body, created first as add_obstacles does
    lay = world.layout
    consts = array.array("d", (wall_radius, friction, elasticity, OBSTACLE, first_hashid))
    return _fastsim.add_static(int(_ffi.cast("uintptr_t", space._space)),
                               int(_ffi.cast("uintptr_t", sb._body)), lay.walls, lay.boxes,
                               lay.cylinders, consts)


def adopt_static(world) -> None:
    """Hand ``world``'s raw obstacle shapes to pymunk (wrapper objects that own them, in the
    space's shape table), so pymunk can pickle the world, its cached contacts included. Done once,
    when a kernel world is first pickled; the shapes themselves do not change."""
    import pymunk

    if world._static is None:
        return
    space, sb, lay = world.space, world.space.static_body, world.layout
    kinds = ([pymunk.Segment] * len(lay.walls) + [pymunk.Poly] * len(lay.boxes)
             + [pymunk.Circle] * len(lay.cylinders))
    others = list(space._shapes)  # the robot's: after the obstacles, as add_obstacles has it
    space._shapes.clear()
    for cls, ptr in zip(kinds, _fastsim.static_release(world._static), strict=True):
        shape = cls.__new__(cls)
        shape._init(sb, _ffi.cast("cpShape *", ptr))  # pymunk's own wrapper setup (owns it)
        shape._space = weakref.ref(space)
        space._shapes[shape] = None
    space._shapes.update(dict.fromkeys(others))
    world._static = None


def overlaps(world) -> bool:
    """:meth:`World.robot_overlaps` in C: does any robot shape intersect another body's shape?"""
    robot = world.robot
    return _fastsim.overlaps(int(_ffi.cast("uintptr_t", world.space._space)),
                             int(_ffi.cast("uintptr_t", robot.body._body)),
                             [int(_ffi.cast("uintptr_t", s._shape)) for s in robot.shapes])




# ---------------------------------------------------------------------- worlds built in C
def _free_space(cp_space) -> None:
    """pymunk.Space's own finaliser (``spacefree`` in pymunk/space.py), for a space made in C."""
    lib = _cp
    shapes: list = []
    h = _ffi.new_handle(shapes)
    lib.cpSpaceEachShape(cp_space, lib.ext_cpSpaceShapeIteratorFunc, h)
    for cp_shape in shapes:
        lib.cpSpaceRemoveShape(lib.cpShapeGetSpace(cp_shape), cp_shape)
        lib.cpShapeSetBody(cp_shape, _ffi.NULL)
    constraints: list = []
    h = _ffi.new_handle(constraints)
    lib.cpSpaceEachConstraint(cp_space, lib.ext_cpSpaceConstraintIteratorFunc, h)
    for c in constraints:
        lib.cpSpaceRemoveConstraint(lib.cpConstraintGetSpace(c), c)
    bodies: list = []
    h = _ffi.new_handle(bodies)
    lib.cpSpaceEachBody(cp_space, lib.ext_cpSpaceBodyIteratorFunc, h)
    for cp_body in bodies:
        lib.cpSpaceRemoveBody(lib.cpBodyGetSpace(cp_body), cp_body)
    lib.cpSpaceFree(cp_space)


def _free_body(cp_body) -> None:
    """pymunk.Body's own finaliser (``freebody`` in pymunk/body.py), for a body made in C."""
    lib = _cp
    lib.cpBodyEachShape(cp_body, lib.ext_cpBodyShapeIteratorFunc, _ffi.NULL)
    lib.cpBodyEachConstraint(cp_body, lib.ext_cpBodyConstraintIteratorFunc, _ffi.NULL)
    cp_space = lib.cpBodyGetSpace(cp_body)
    if cp_space != _ffi.NULL:
        lib.cpSpaceRemoveBody(cp_space, cp_body)
    lib.cpBodyFree(cp_body)


def wrap_space(address: int):
    """A ``pymunk.Space`` for a cpSpace made in C (it owns and frees it from now on), as
    ``pymunk.Space()`` sets one up."""
    import pymunk

    space = pymunk.Space.__new__(pymunk.Space)
    space.threaded = False
    space._space = _ffi.gc(_ffi.cast("cpSpace *", address), _free_space)
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


def wrap_body(address: int, space, static: bool = False):
    """A ``pymunk.Body`` for a cpBody made in C and already in ``space``'s cpSpace (it owns and
    frees it from now on): ``space.static_body`` when ``static``, else one of ``space.bodies``."""
    import pymunk

    body = pymunk.Body.__new__(pymunk.Body)
    body._body = _ffi.gc(_ffi.cast("cpBody *", address), _free_body)
    body._space = weakref.ref(space)
    body._constraints = weakref.WeakKeyDictionary()
    body._shapes = {}
    body._data_handle = _ffi.new_handle(body)
    _cp.cpBodySetUserData(body._body, body._data_handle)
    if static:
        space._static_body = body
    else:
        space._bodies[body] = None
    return body


def wrap_shape(cls, address: int, body, space):
    """A pymunk shape of class ``cls`` for a cpShape made in C and already in ``space`` (it owns
    and frees it from now on), as :func:`adopt_static` wraps the obstacles."""
    shape = cls.__new__(cls)
    shape._init(body, _ffi.cast("cpShape *", address))
    shape._space = weakref.ref(space)
    space._shapes[shape] = None
    return shape
