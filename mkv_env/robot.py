"""MK-V dynamics: chassis body, wheel contact model and the two DC motors.

The chassis is a pymunk body; pymunk resolves its contacts with the world. The wheels are not
bodies: each physics substep this module applies the wheel-floor impulses itself, solving three
velocity constraints together (drive-wheel lateral, drive-wheel rolling, steering-wheel lateral)
and projecting the solution on each wheel's friction circle (traction limit ``mu * N``). The drive
motor is integrated implicitly inside that solve (its back-EMF acts as extra inertia), so the
result is stable at any substep and the blocked wheel stalls or spins by the true criterion:
stall force against traction. The caster carries load only.

Everything here is pure float arithmetic on a handful of values, read from and written to the
pymunk body once per substep: this is the simulator's hot path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pymunk

from mkv_env.params import GRAVITY_MPS2, RobotParams

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


class Robot:
    """The MK-V chassis in a pymunk space, with its wheel and motor model.

    Args:
        space: the world it lives in.
        params: geometry, mass and motors.
        position: (x, y) [m]; heading: [rad].
    """

    def __init__(self, space: pymunk.Space, params: RobotParams, position, heading: float):
        p = self.params = params
        hl, hw = p.length_m / 2, p.width_m / 2
        inertia = p.mass_kg * (p.length_m**2 + p.width_m**2) / 12.0
        self.body = pymunk.Body(p.mass_kg, inertia)
        self.body.position = position
        self.body.angle = heading
        chassis = pymunk.Poly(self.body, [(-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw)], radius=0.0)
        chassis.collision_type = CHASSIS
        g, r = p.bumper_gap_m, 0.008
        front, rear = hl + g, -hl - g
        fl = pymunk.Segment(self.body, (front, 0.0), (front - 0.03, hw), r)
        fr = pymunk.Segment(self.body, (front, 0.0), (front - 0.03, -hw), r)
        rb = pymunk.Segment(self.body, (rear, -hw * 0.8), (rear, hw * 0.8), r)
        for shape, ctype in ((fl, BUMP_FL), (fr, BUMP_FR), (rb, BUMP_REAR)):
            shape.collision_type = ctype
        self.shapes = (chassis, fl, fr, rb)
        for s in self.shapes:
            s.friction = p.chassis_friction
            s.elasticity = 0.0
            s.filter = ROBOT_FILTER
        space.add(self.body, *self.shapes)
        self.state = WheelState()
        self._mu_scale = 1.0
        self._precompute()

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

    def set_floor_friction_scale(self, scale: float) -> None:
        """Multiply the tyre friction (slippery floor patches under the robot)."""
        self._mu_scale = scale

    # ------------------------------------------------------------------ hot path
    def substep(self, drive_cmd: int, steer_cmd: int, dt: float) -> None:
        """Advance motors and apply wheel impulses for one physics substep of ``dt`` seconds.

        ``drive_cmd``/``steer_cmd`` are -1, 0 or +1 (steer +1 = left). Call ``space.step(dt)``
        afterwards to integrate positions and resolve contacts.
        """
        p = self.params
        st = self.state
        body = self.body
        vx, vy = body.velocity
        om = body.angular_velocity
        th = body.angle
        c, s = math.cos(th), math.sin(th)
        u = c * vx + s * vy  # forward velocity of the chassis centre
        w = -s * vx + c * vy  # leftward velocity
        xd, xs = p.drive_x_m, p.steer_x_m
        rw = p.drive_wheel_radius_m

        # Free-rolling steering wheel encoder: the actual motion after last substep's contacts.
        delta = st.steer
        cd, sd = math.cos(delta), math.sin(delta)
        st.roller_angle += (cd * u + sd * (w + om * xs)) * dt / p.steer_wheel_radius_m

        # Steering motor, implicit in its rate; dry friction opposes motion; stops clamp it.
        vs = self._s_v * steer_cmd
        torque = self._s_k * vs / self._s_r
        rate = st.steer_rate
        fric = p.steer_coulomb_nm
        if rate > 1e-6 or (rate >= -1e-6 and torque > fric):
            torque -= fric
        elif rate < -1e-6 or torque < -fric:
            torque += fric
        else:
            torque = 0.0
        rate = (self._s_j * rate + dt * torque) / (self._s_j + dt * self._s_c)
        delta += rate * dt
        lim = p.steer_limit_rad
        if delta > lim:
            delta, rate = lim, 0.0
        elif delta < -lim:
            delta, rate = -lim, 0.0
        st.steer, st.steer_rate = delta, rate
        st.steer_current = (vs - self._s_k * rate) / self._s_r
        cd, sd = math.cos(delta), math.sin(delta)

        # Drive motor, implicit: over the substep the wheel behaves as inertia jp with momentum
        # j*omega + dt*k*V/R; the floor impulse lam2 then acts on that.
        vd = self._d_v * drive_cmd
        jp = self._d_j + dt * self._d_c
        ww = (self._d_j * st.drive_omega + dt * self._d_k * vd / self._d_r) / jp

        im, iI, iJ = self._im, self._iI, 1.0 / jp
        # constraint velocities: drive lateral, drive rolling slip, steering-wheel lateral
        v1 = w + om * xd
        v2 = u - ww * rw
        v3 = -sd * u + cd * (w + om * xs)
        k11 = im + xd * xd * iI
        k22 = im + rw * rw * iJ
        k33 = im + cd * cd * xs * xs * iI
        k13 = cd * im + xd * cd * xs * iI
        k23 = -sd * im
        # Solve K lam = -v (K symmetric, k12 = 0) by Cramer's rule.
        det = k11 * (k22 * k33 - k23 * k23) - k13 * k13 * k22
        r1, r2, r3 = -v1, -v2, -v3
        l1 = (r1 * (k22 * k33 - k23 * k23) + k13 * (r2 * k23 - r3 * k22)) / det
        l2 = (k11 * (r2 * k33 - r3 * k23) - k13 * k13 * r2 + k13 * r1 * k23) / det
        l3 = (k11 * (k22 * r3 - k23 * r2) - r1 * k13 * k22) / det
        mu = p.tire_friction * self._mu_scale
        cap_d = mu * self._n_drive * dt
        cap_s = mu * self._n_steer * dt
        if l1 * l1 + l2 * l2 > cap_d * cap_d or abs(l3) > cap_s:
            # Sliding: projected Gauss-Seidel on the friction circle / interval.
            l1 = l2 = l3 = 0.0
            a1, a2, a3 = v1, v2, v3
            for _ in range(8):
                n1 = l1 - a1 / k11
                n2 = l2 - a2 / k22
                norm = math.hypot(n1, n2)
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
        u += im * (l2 - sd * l3)
        w += im * (l1 + cd * l3)
        om += iI * (xd * l1 + cd * xs * l3)
        ww -= iJ * rw * l2
        st.drive_omega = ww
        st.drive_angle += ww * dt
        st.drive_current = (vd - self._d_k * ww) / self._d_r
        body.velocity = (c * u - s * w, s * u + c * w)
        body.angular_velocity = om

    # ------------------------------------------------------------------ queries
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
