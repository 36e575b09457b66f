"""MK-V dynamics: chassis body, wheel contact model and the two DC motors.

The chassis is a pymunk body; pymunk resolves its contacts with the world. The wheels are not
bodies: each physics substep this module applies the wheel-floor impulses itself, solving three
velocity constraints together (drive-wheel lateral, drive-wheel rolling, steering-wheel lateral)
and projecting the solution on each wheel's friction circle (traction limit ``mu * N``). The drive
motor is integrated implicitly inside that solve (its back-EMF acts as extra inertia), so the
result is stable at any substep and the blocked wheel stalls or spins by the true criterion:
stall force against traction. The caster carries load only.

Everything here is pure float arithmetic on a handful of values, read from and written to the
pymunk body once per substep: this is the simulator's hot path. It exists twice: the Python loop
below (readable, the reference) and the same loop in C (``mkv_env/_native/wheels.c``, built by
setup.py; about 4x faster), written operation for operation so both give the same bits
(``tests/mkv_env/test_kernel.py`` compares whole episodes). Without a C compiler the Python loop
runs and nothing else changes.
"""

from __future__ import annotations

import array
import math
from dataclasses import dataclass

import pymunk

# pymunk's own cffi layer (the same calls its properties make, minus the wrappers) and the same
# loop compiled (setup.py builds it): None when absent or when mkv_env.chipmunk's import-time
# check finds the installed pymunk differs from what they assume
from mkv_env.chipmunk import address as _address
from mkv_env.chipmunk import addresses as _addresses
from mkv_env.chipmunk import c_object as _c
from mkv_env.chipmunk import cp as _cp
from mkv_env.chipmunk import fastsim as _fastsim
from mkv_env.chipmunk import pending as _pending
from mkv_env.layouts import pack as _pack
from mkv_env.params import GRAVITY_MPS2, RobotParams


def bind_kernel(hypot=math.hypot) -> None:
    """Hand the compiled loop Chipmunk's entry points (from pymunk's cffi module) and the
    ``hypot`` it calls back (``math.hypot``; tests pass a counting wrapper)."""
    _fastsim.bind(*_addresses(
        "cpBodyGetVelocity", "cpBodyGetAngularVelocity", "cpBodyGetAngle", "cpBodySetForce",
        "cpBodySetTorque", "cpSpaceStep"), hypot)


if _fastsim is not None and _cp is not None:
    bind_kernel()
else:
    _fastsim = None

#: Which implementation of :meth:`Robot.advance` runs by default: ``"c"`` (the compiled loop) or
#: ``"python"`` (the reference loop, on pymunk's public API only). Both give the same bits
#: (tests/mkv_env/test_kernel.py).
DEFAULT_KERNEL = "c" if _fastsim is not None else "python"

# Collision types of the robot's shapes (obstacles use OBSTACLE).
CHASSIS, BUMP_FL, BUMP_FR, BUMP_REAR, OBSTACLE = 1, 2, 3, 4, 10
#: The robot's shapes share a group, so queries made with this filter ignore the robot.
ROBOT_FILTER = pymunk.ShapeFilter(group=1)


@dataclass
class WheelState:
    """Internal states that are not part of the rigid body."""

    drive_omega: float = 0.0  # drive wheel speed [rad/s]
    drive_angle: float = 0.0  # accumulated drive wheel angle [rad]
    roller_angle: float = 0.0  # accumulated steering-wheel rolling angle [rad]
    steer: float = 0.0  # steering angle [rad], left positive
    steer_rate: float = 0.0  # [rad/s]
    drive_current: float = 0.0  # [A] at the end of the last substep
    steer_current: float = 0.0  # [A]
    drive_budget: float = 0.0  # traction impulse left unused by the last substep [N s]


def moment_of_inertia(p: RobotParams) -> float:
    """The chassis's moment of inertia about its centre [kg m^2] (a uniform rectangle)."""
    return p.mass_kg * (p.length_m**2 + p.width_m**2) / 12.0


def kernel_constants(p: RobotParams) -> array.array:
    """The compiled loop's constants for robots of parameters ``p``, in the order of
    ``_native/kernel.h``'s ``K_*`` enum (each computed as :meth:`Robot._precompute` computes it)."""
    m = p.mass_kg
    moment = moment_of_inertia(p)
    dm, sm = p.drive_motor, p.steer_motor
    weight = m * GRAVITY_MPS2
    k = _pack("K", {
        "XD": p.drive_x_m, "XS": p.steer_x_m, "RW": p.drive_wheel_radius_m,
        "INV_RS": 1.0 / p.steer_wheel_radius_m, "LIM": p.steer_limit_rad, "IM": 1.0 / m,
        "II": 1.0 / moment, "TIRE_MU": p.tire_friction,
        "N_DRIVE": p.drive_load_fraction * weight, "N_STEER": p.steer_load_fraction * weight,
        "S_V": sm.supply_v, "S_K": sm.k_nm_per_a, "S_R": sm.resistance_ohm,
        "S_J": sm.inertia_kgm2, "S_C": sm.k_nm_per_a**2 / sm.resistance_ohm + sm.viscous_nms,
        "FRIC": p.steer_coulomb_nm, "D_V": dm.supply_v, "D_K": dm.k_nm_per_a,
        "D_R": dm.resistance_ohm, "D_J": dm.inertia_kgm2,
        "D_C": dm.k_nm_per_a**2 / dm.resistance_ohm + dm.viscous_nms, "MASS": m,
        "MOMENT": moment})
    return k


BUMPER_RADIUS_M = 0.008
"""Radius of the three bumper segments [m]."""


def shape_geometry(p: RobotParams) -> tuple:
    """The robot's shapes in its body frame: the chassis polygon's 4 vertices, then the front-left,
    front-right and rear bumper segments as ((ax, ay), (bx, by)), and the bumpers' radius (what
    :class:`Robot` builds, and what a reset in C builds: mkv_env.kernel.reset_constants)."""
    hl, hw = p.length_m / 2, p.width_m / 2
    g = p.bumper_gap_m
    front, rear = hl + g, -hl - g
    chassis = ((-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw))
    bumpers = (((front, 0.0), (front - 0.03, hw)), ((front, 0.0), (front - 0.03, -hw)),
               ((rear, -hw * 0.8), (rear, hw * 0.8)))
    return chassis, bumpers, BUMPER_RADIUS_M


def _steer_substep(delta, rate, s_drive, fric, s_j, s_den, dt, lim):
    """One substep of the steering motor (:meth:`Robot.advance`): implicit in its rate, dry
    friction, the stops clamp it. Returns the new (angle, rate)."""
    torque = s_drive
    if rate > 1e-6 or (rate >= -1e-6 and torque > fric):
        torque -= fric
    elif rate < -1e-6 or torque < -fric:
        torque += fric
    else:
        torque = 0.0
    rate = (s_j * rate + dt * torque) / s_den
    delta += rate * dt
    if delta > lim:
        delta, rate = lim, 0.0
    elif delta < -lim:
        delta, rate = -lim, 0.0
    return delta, rate


def _slide(v1, v2, v3, k11, k22, k33, k13, k23, cap_d, cap_s, hypot):
    """The wheels sliding (:meth:`Robot.advance`): projected Gauss-Seidel on the drive wheel's
    friction circle and the steering wheel's friction interval, 8 sweeps. Returns (l1, l2, l3)."""
    l1 = l2 = l3 = 0.0
    a1, a2, a3 = v1, v2, v3
    for _it in range(8):
        n1 = l1 - a1 / k11
        n2 = l2 - a2 / k22
        norm = hypot(n1, n2)
        if norm > cap_d:
            n1, n2 = n1 * cap_d / norm, n2 * cap_d / norm
        d1, d2 = n1 - l1, n2 - l2
        l1, l2 = n1, n2
        a1 += k11 * d1
        a2 += k22 * d2
        a3 += k13 * d1 + k23 * d2
        n3 = min(max(l3 - a3 / k33, -cap_s), cap_s)
        d3 = n3 - l3
        l3 = n3
        a1 += k13 * d3
        a2 += k23 * d3
    return l1, l2, l3


class Robot:
    """The MK-V chassis in a pymunk space, with its wheel and motor model.

    Args:
        space: the world it lives in.
        params: geometry, mass and motors.
        position: (x, y) [m]; heading: [rad].
    """

    def __init__(self, space: pymunk.Space, params: RobotParams, position, heading: float):
        p = self.params = params
        self.body = pymunk.Body(p.mass_kg, moment_of_inertia(p))
        self.body.position = position
        self.body.angle = heading
        verts, bumpers, r = shape_geometry(p)
        chassis = pymunk.Poly(self.body, list(verts), radius=0.0)
        fl, fr, rb = (pymunk.Segment(self.body, a, b, r) for a, b in bumpers)
        self.shapes = (chassis, fl, fr, rb)
        for s, ctype in zip(self.shapes, (CHASSIS, BUMP_FL, BUMP_FR, BUMP_REAR), strict=True):
            if _cp is not None:  # the calls pymunk's property setters make, without their wrappers
                _cp.cpShapeSetCollisionType(_c(s), ctype)
                _cp.cpShapeSetFriction(_c(s), p.chassis_friction)
                _cp.cpShapeSetElasticity(_c(s), 0.0)
                _cp.cpShapeSetFilter(_c(s), ROBOT_FILTER)
            else:  # pragma: no cover - pymunk builds without cffi
                s.collision_type, s.friction, s.elasticity = ctype, p.chassis_friction, 0.0
                s.filter = ROBOT_FILTER
        space.add(self.body, *self.shapes)
        #: the wheels' state; None while the compiled step kernel of an env holds it
        #: (:meth:`hand_over` / :meth:`load_state`)
        self._state: WheelState | None = WheelState()
        self._mu_scale = 1.0
        self.kernel = DEFAULT_KERNEL  # "c" or "python" (same results; see DEFAULT_KERNEL)
        self._ptrs: tuple | None = None  # (space, cpBody address, cpSpace address)
        self._precompute()

    @classmethod
    def adopted(cls, params: RobotParams, body: pymunk.Body, shapes: tuple,
                kernel: str) -> Robot:
        """A robot around a body and shapes built elsewhere (a reset in the compiled kernel:
        :func:`mkv_env.kernel.adopt_world`), already in their space: what ``__init__`` sets
        besides building them."""
        robot = cls.__new__(cls)
        robot.params, robot.body, robot.shapes = params, body, shapes
        robot._state = WheelState()
        robot._mu_scale = 1.0
        robot.kernel = kernel
        robot._ptrs = None
        robot._precompute()
        return robot

    @property
    def state(self) -> WheelState:
        """The wheels' and motors' internal state. While an env's compiled step kernel holds it
        (:meth:`hand_over`) reading it is an error: ``env.unwrapped.world`` brings it back."""
        if self._state is None:
            raise RuntimeError(
                "this robot's wheel state is held by the compiled kernel stepping it: read it "
                "as env.unwrapped.world.robot.state (taking the env's world brings it back)")
        return self._state

    @state.setter
    def state(self, value: WheelState) -> None:
        self._state = value

    #: The names :meth:`to_state` gives and :meth:`load_state` takes: the wheel state's fields,
    #: then the floor friction scale under the drive wheel.
    STATE = (*WheelState.__dataclass_fields__, "mu_scale")

    def to_state(self) -> dict:
        """The robot's own state besides its pymunk body, by name (:data:`STATE`)."""
        st = self.state
        out = {name: getattr(st, name) for name in WheelState.__dataclass_fields__}
        out["mu_scale"] = self._mu_scale
        return out

    def load_state(self, state: dict) -> None:
        """Take a state another owner has reached (an env's compiled step kernel), by name
        (:data:`STATE`); ends a :meth:`hand_over`."""
        st = self._state if self._state is not None else WheelState()
        for name in WheelState.__dataclass_fields__:
            setattr(st, name, state[name])
        self._state = st
        self._mu_scale = state["mu_scale"]

    def hand_over(self) -> None:
        """The wheel state now lives elsewhere (an env's compiled step kernel took it with
        :meth:`to_state`): :attr:`state` refuses to be read until :meth:`load_state`, so no
        reader sees a stale copy."""
        self._state = None

    def _precompute(self) -> None:
        p = self.params
        m = p.mass_kg
        self._im = 1.0 / m
        self._iI = 1.0 / self.body.moment
        weight = m * GRAVITY_MPS2
        self._n_drive = p.drive_load_fraction * weight
        self._n_steer = p.steer_load_fraction * weight
        dm, sm = p.drive_motor, p.steer_motor
        self._d_k, self._d_r, self._d_v = dm.k_nm_per_a, dm.resistance_ohm, dm.supply_v
        self._d_c = dm.k_nm_per_a**2 / dm.resistance_ohm + dm.viscous_nms
        self._d_j = dm.inertia_kgm2
        self._s_k, self._s_r, self._s_v = sm.k_nm_per_a, sm.resistance_ohm, sm.supply_v
        self._s_c = sm.k_nm_per_a**2 / sm.resistance_ohm + sm.viscous_nms
        self._s_j = sm.inertia_kgm2
        if _fastsim is not None:
            self.kernel_constants = kernel_constants(p)
            assert self.kernel_constants[-1] == self.body.moment

    def pointers(self, space) -> tuple:
        """(space, address of the cpBody, address of ``space``'s cpSpace), cached, for the
        compiled loop. Never pickled: a copy has new Chipmunk objects."""
        ptrs = self._ptrs
        if ptrs is None or ptrs[0] is not space:
            ptrs = self._ptrs = (space, _address(self.body), _address(space))
        return ptrs

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_ptrs"] = None
        return state

    def __setstate__(self, state):
        state.pop("_sync", None)  # (pickled when the env's kernel was called back through it)
        self.__dict__.update(state)

    def can_use_c(self, space) -> bool:
        """True when :meth:`advance` on ``space`` runs the compiled loop."""
        return self.kernel == "c" and _fastsim is not None and not _pending(space)

    @property
    def floor_friction_scale(self) -> float:
        """The tyre friction's multiplier under the drive wheel (slippery floor patches)."""
        return self._mu_scale

    def set_floor_friction_scale(self, scale: float) -> None:
        """Multiply the tyre friction (slippery floor patches under the robot)."""
        self._mu_scale = scale

    # ------------------------------------------------------------------ hot path
    def _substep_constants(self, drive_cmd: int, steer_cmd: int, dt: float) -> tuple:
        """The constants of :meth:`advance`'s Python loop for one control period's commands."""
        p = self.params
        xd, xs = p.drive_x_m, p.steer_x_m
        rw = p.drive_wheel_radius_m
        inv_rs = 1.0 / p.steer_wheel_radius_m
        lim = p.steer_limit_rad
        im, iI = self._im, self._iI
        k11 = im + xd * xd * iI
        mu = p.tire_friction * self._mu_scale
        cap_d = mu * self._n_drive * dt
        cap_s = mu * self._n_steer * dt
        # steering motor constants for this command
        vs = self._s_v * steer_cmd
        s_drive = self._s_k * vs / self._s_r
        s_j = self._s_j
        s_den = s_j + dt * self._s_c
        fric = p.steer_coulomb_nm
        s_k_over_r = self._s_k / self._s_r
        vs_over_r = vs / self._s_r
        # drive motor: implicit inertia jp, momentum j*omega + dt*k*V/R
        vd = self._d_v * drive_cmd
        d_j = self._d_j
        jp = d_j + dt * self._d_c
        d_push = dt * self._d_k * vd / self._d_r
        iJ = 1.0 / jp
        k22 = im + rw * rw * iJ
        d_k_over_r = self._d_k / self._d_r
        vd_over_r = vd / self._d_r
        return (xd, xs, rw, inv_rs, lim, im, iI, k11, cap_d, cap_s, s_drive, s_j, s_den, fric,
                s_k_over_r, vs_over_r, d_j, jp, d_push, iJ, k22, d_k_over_r, vd_over_r)

    def advance(self, drive_cmd: int, steer_cmd: int, dt: float, n: int, space) -> None:
        """Run ``n`` physics substeps of ``dt`` seconds with constant motor commands.

        ``drive_cmd``/``steer_cmd`` are -1, 0 or +1 (steer +1 = left). Each substep: steering
        motor, drive motor (implicit), wheel-floor impulses, then ``space.step(dt)`` for
        positions and contacts. With ``self.kernel == "c"`` the compiled copy of this loop runs
        (``mkv_env/_native/wheels.c``, the same operations in the same order, so the same bits);
        otherwise the Python loop below, the reference: state in locals, the body read and
        pushed through pymunk's public properties only.
        """
        if self.kernel == "c" and _fastsim is not None and not _pending(space):
            _, body_ptr, space_ptr = self.pointers(space)
            _fastsim.advance(self.kernel_constants, body_ptr, space_ptr, drive_cmd, steer_cmd, dt,
                             n, self._mu_scale, self.state)
            return
        st = self.state
        (xd, xs, rw, inv_rs, lim, im, iI, k11, cap_d, cap_s, s_drive, s_j, s_den, fric, s_k_over_r,
         vs_over_r, d_j, jp, d_push, iJ, k22, d_k_over_r, vd_over_r) = self._substep_constants(
            drive_cmd, steer_cmd, dt)

        ww, delta, rate = st.drive_omega, st.steer, st.steer_rate
        drive_angle, roller_angle = st.drive_angle, st.roller_angle
        budget = st.drive_budget
        jw_over_rw = d_j / rw
        cd, sd = math.cos(delta), math.sin(delta)
        k33 = im + cd * cd * xs * xs * iI
        k13 = cd * im + xd * cd * xs * iI
        k23 = -sd * im
        steer_idle = steer_cmd == 0 and rate == 0.0
        cos, sin, hypot = math.cos, math.sin, math.hypot
        body, step = self.body, space.step
        m_dt, i_dt = self.params.mass_kg / dt, body.moment / dt

        for _ in range(n):
            vx, vy = body.velocity
            om = body.angular_velocity
            th = body.angle
            c, s = cos(th), sin(th)
            u = c * vx + s * vy  # forward velocity of the chassis centre
            w = c * vy - s * vx  # leftward velocity
            # free-rolling steering wheel encoder: the actual motion after the last contacts
            roller_angle += (cd * u + sd * (w + om * xs)) * dt * inv_rs
            # The solve below cannot see obstacles; after contacts the chassis may have moved
            # less than the wheel rolled. Reconcile the wheel with the chassis's actual motion,
            # within the traction the last substep left unused: a blocked wheel with traction to
            # spare stops (stall), one without keeps spinning.
            if budget > 0.0:
                slip = u / rw - ww
                cap = budget / jw_over_rw
                ww += slip if -cap <= slip <= cap else (cap if slip > 0 else -cap)
            # encoder and current see the wheel's reconciled speed over the last substep
            drive_angle += ww * dt
            ww_seen = ww

            if not steer_idle:
                delta, rate = _steer_substep(delta, rate, s_drive, fric, s_j, s_den, dt, lim)
                steer_idle = steer_cmd == 0 and rate == 0.0
                cd, sd = cos(delta), sin(delta)
                k33 = im + cd * cd * xs * xs * iI
                k13 = cd * im + xd * cd * xs * iI
                k23 = -sd * im

            ww = (d_j * ww + d_push) / jp
            # constraint velocities: drive lateral, drive rolling slip, steering-wheel lateral
            v1 = w + om * xd
            v2 = u - ww * rw
            v3 = cd * (w + om * xs) - sd * u
            # solve K lam = -v (K symmetric, k12 = 0) by Cramer's rule
            a = k22 * k33 - k23 * k23
            det = k11 * a - k13 * k13 * k22
            l1 = (-v1 * a + k13 * (v3 * k22 - v2 * k23)) / det
            l2 = (k11 * (v3 * k23 - v2 * k33) + k13 * (k13 * v2 - v1 * k23)) / det
            l3 = (k11 * (k23 * v2 - k22 * v3) + v1 * k13 * k22) / det
            used = l1 * l1 + l2 * l2
            if used > cap_d * cap_d or abs(l3) > cap_s:
                l1, l2, l3 = _slide(v1, v2, v3, k11, k22, k33, k13, k23, cap_d, cap_s, hypot)
                used = l1 * l1 + l2 * l2
            budget = cap_d - math.sqrt(used)
            # The wheel impulses go to Chipmunk as force and torque: it integrates positions
            # *before* solving contacts, so velocities set directly would push the robot into
            # walls; forces enter its velocity phase, where contacts can still cancel them.
            du = im * (l2 - sd * l3)
            dw = im * (l1 + cd * l3)
            body.force = ((c * du - s * dw) * m_dt, (s * du + c * dw) * m_dt)
            body.torque = (xd * l1 + cd * xs * l3) * iI * i_dt
            ww -= iJ * rw * l2
            step(dt)

        st.drive_omega, st.steer, st.steer_rate = ww, delta, rate
        st.drive_angle, st.roller_angle = drive_angle, roller_angle
        st.drive_budget = budget
        st.drive_current = vd_over_r - d_k_over_r * ww_seen
        st.steer_current = vs_over_r - s_k_over_r * rate

    # ------------------------------------------------------------------ queries
    def pose(self) -> tuple[float, float, float]:
        """(x [m], y [m], heading [rad], not wrapped) of the chassis centre."""
        if _cp is not None:
            b = _c(self.body)
            v = _cp.cpBodyGetPosition(b)
            return v.x, v.y, _cp.cpBodyGetAngle(b)
        x, y = self.body.position
        return x, y, self.body.angle

    def angle(self) -> float:
        """Heading [rad], not wrapped."""
        return _cp.cpBodyGetAngle(_c(self.body)) if _cp is not None else self.body.angle

    def forward_speed(self) -> float:
        """Chassis speed along its heading [m/s] (ground truth)."""
        vx, vy = self.body.velocity
        th = self.body.angle
        return math.cos(th) * vx + math.sin(th) * vy

    def corners(self) -> list[tuple[float, float]]:
        """World coordinates of the chassis outline (for drawing and containment tests)."""
        hl, hw = self.params.length_m / 2, self.params.width_m / 2
        lw = self.body.local_to_world
        return [tuple(lw((x, y))) for x, y in ((-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw))]
