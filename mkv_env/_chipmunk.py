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

from mkv_env import chipmunk
from mkv_env.chipmunk import address, c_object, shapes_table
from mkv_env.chipmunk import addresses as _addresses
from mkv_env.chipmunk import cp as _cp
from mkv_env.chipmunk import ffi as _ffi
from mkv_env.robot import BUMP_FL, BUMP_FR, BUMP_REAR, CHASSIS, OBSTACLE, _fastsim

#: True when the extension and pymunk's cffi layer are both there and match
#: (:mod:`mkv_env.chipmunk` checks them at import).
AVAILABLE = _fastsim is not None and _cp is not None and hasattr(_fastsim, "add_static")


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
    _fastsim.bind_reset(*_addresses(
        "cpSpaceNew", "cpSpaceFree", "cpSpaceSetIterations", "cpSpaceSetDamping", "cpBodyNew",
        "cpBodyNewStatic", "cpBodyFree", "cpSpaceAddBody", "cpSpaceRemoveBody",
        "cpBodySetPosition", "cpBodySetAngle", "cpShapeSetFilter",
        "cpSpaceReindexShapesForBody", "cpSpaceAddCollisionHandler"))
    HANDLER_OFFSETS = tuple(_ffi.offsetof("cpCollisionHandler", f)
                            for f in ("beginFunc", "separateFunc", "userData"))


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
        h = _cp.cpSpaceAddCollisionHandler(c_object(space), ctype, OBSTACLE)
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
    return _fastsim.add_static(address(space), address(sb), lay.walls, lay.boxes, lay.cylinders,
                               consts)


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
    table = shapes_table(space)
    others = list(table)  # the robot's: after the obstacles, as add_obstacles has it
    table.clear()
    for cls, ptr in zip(kinds, _fastsim.static_release(world._static), strict=True):
        chipmunk.wrap_shape(cls, ptr, sb, space)  # pymunk's own wrapper setup (owns it)
    table.update(dict.fromkeys(others))
    world._static = None


def overlaps(world) -> bool:
    """:meth:`World.robot_overlaps` in C: does any robot shape intersect another body's shape?"""
    robot = world.robot
    return _fastsim.overlaps(address(world.space), address(robot.body),
                             [address(s) for s in robot.shapes])
