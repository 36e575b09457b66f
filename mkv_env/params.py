"""Physical parameters of the MK-V robot and its world, with units.

Body frame: x forward, y to the left, origin at the chassis centre; angles counter-clockwise.
Every number here is a documented default that a user can override through ``gymnasium.make``
kwargs (see :class:`mkv_env.envs.MKVEnv`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

GRAVITY_MPS2 = 9.81


@dataclass(frozen=True)
class DCMotor:
    """A permanent-magnet DC motor seen at the wheel (gearbox folded in).

    current i = (V - k * omega) / R; torque = k * i. With the supply removed ("off") the
    armature stays connected (V = 0), so back-EMF brakes the wheel: it coasts and is damped.
    """

    supply_v: float
    """Supply voltage [V] applied as +V, 0 or -V by the three-valued command."""
    resistance_ohm: float
    """Armature resistance [ohm]; stall current = supply_v / resistance_ohm."""
    k_nm_per_a: float
    """Torque constant = back-EMF constant at the output shaft [N m / A] = [V s / rad]."""
    viscous_nms: float
    """Viscous friction at the output shaft [N m s / rad]."""
    inertia_kgm2: float
    """Rotor + gearbox inertia reflected to the output shaft [kg m^2]."""

    @property
    def stall_current_a(self) -> float:
        return self.supply_v / self.resistance_ohm

    @property
    def stall_torque_nm(self) -> float:
        return self.k_nm_per_a * self.stall_current_a

    @property
    def no_load_speed_rps(self) -> float:
        return self.supply_v / self.k_nm_per_a


@dataclass(frozen=True)
class RobotParams:
    """Geometry, mass and drivetrain of the MK-V (three wheels, tricycle layout)."""

    mass_kg: float = 3.0
    """Total mass [kg]."""
    length_m: float = 0.30
    """Chassis length along x [m]."""
    width_m: float = 0.22
    """Chassis width along y [m]."""
    bumper_gap_m: float = 0.012
    """Bumper standoff from the chassis front/rear faces [m]."""
    drive_x_m: float = -0.09
    """Drive wheel contact point on the centre line [m] (rear)."""
    steer_x_m: float = 0.09
    """Steering wheel contact point on the centre line [m] (front)."""
    caster_xy_m: tuple[float, float] = (0.02, -0.08)
    """Caster position [m]; it carries load but adds no lateral constraint."""
    drive_wheel_radius_m: float = 0.03
    steer_wheel_radius_m: float = 0.025
    drive_load_fraction: float = 0.45
    """Share of the weight on the drive wheel; sets its traction limit."""
    steer_load_fraction: float = 0.30
    """Share of the weight on the steering wheel; the caster carries the rest."""
    tire_friction: float = 0.9
    """Tyre-floor friction coefficient on the normal floor (friction circle)."""
    steer_limit_rad: float = math.radians(35.0)
    """Mechanical stops of the steering wheel [rad]."""
    steer_coulomb_nm: float = 0.08
    """Dry friction of the steering pivot [N m]."""
    drive_motor: DCMotor = DCMotor(
        supply_v=6.0, resistance_ohm=12.0, k_nm_per_a=0.6, viscous_nms=0.002, inertia_kgm2=4e-4
    )
    """Drive motor: 0.5 A stall current, 10 rad/s (0.30 m/s) no-load, 10 N stall force at the
    tyre: below the 11.9 N traction limit on the normal floor (blocked head-on it stalls), above
    it on slippery patches or under side load (blocked, it spins)."""
    steer_motor: DCMotor = DCMotor(
        supply_v=6.0, resistance_ohm=15.0, k_nm_per_a=3.0, viscous_nms=0.05, inertia_kgm2=2e-3
    )
    """Steering motor: 0.4 A stall current at the stops, ~2 rad/s no-load slew."""
    chassis_friction: float = 0.4
    """Coulomb friction of the chassis/bumpers against obstacles."""

    def replace(self, **changes) -> RobotParams:
        return replace(self, **changes)


@dataclass(frozen=True)
class ChannelSpec:
    """How one sensor channel turns truth into a reading: bias, Gaussian noise, quantisation."""

    low: float
    high: float
    noise_std: float = 0.0
    quantum: float = 0.0
    bias: float = 0.0
    unit: str = ""
    doc: str = ""


#: Default sensor suite, in observation order. Readings are clipped to [low, high].
DEFAULT_CHANNELS: dict[str, ChannelSpec] = {
    "drive_ticks": ChannelSpec(-60, 60, 0.0, 1.0, 0.0, "ticks/period",
                               "drive-wheel encoder ticks counted in the last control period"),
    "roller_ticks": ChannelSpec(-60, 60, 0.0, 1.0, 0.0, "ticks/period",
                                "encoder ticks of the free-rolling steering wheel"),
    "steer_angle": ChannelSpec(-0.8, 0.8, 0.005, 0.0061, 0.0, "rad",
                               "steering potentiometer, left positive (10-bit ADC)"),
    "compass": ChannelSpec(-math.pi, math.pi, math.radians(2.0), math.radians(1.0), 0.0, "rad",
                           "compass heading, counter-clockwise from +x, wrapped"),
    "bump_front_left": ChannelSpec(0, 1, 0.0, 0.0, 0.0, "bool", "front-left bump switch"),
    "bump_front_right": ChannelSpec(0, 1, 0.0, 0.0, 0.0, "bool", "front-right bump switch"),
    "bump_rear": ChannelSpec(0, 1, 0.0, 0.0, 0.0, "bool", "rear bump switch"),
    "drive_current": ChannelSpec(-1.2, 1.2, 0.01, 0.0024, 0.0, "A",
                                 "drive motor current (10-bit ADC over +-1.2 A)"),
    "steer_current": ChannelSpec(-1.0, 1.0, 0.01, 0.002, 0.0, "A",
                                 "steering motor current (10-bit ADC over +-1 A)"),
    "battery": ChannelSpec(0.0, 8.0, 0.02, 0.0078, 0.0, "V",
                           "battery voltage, sags with load (a superfluous channel)"),
}


def channel_specs(overrides=None, noise_scale: float = 1.0) -> dict[str, ChannelSpec]:
    """Default channels with per-channel overrides and a global noise multiplier.

    ``overrides`` maps a channel name to a dict of :class:`ChannelSpec` fields, e.g.
    ``{"compass": {"bias": 0.1, "noise_std": 0.0}}``.
    """
    if not (math.isfinite(noise_scale) and noise_scale >= 0):
        raise ValueError(f"sensor_noise must be a finite number >= 0, got {noise_scale!r}")
    specs = dict(DEFAULT_CHANNELS)
    allowed = {f.name for f in fields(ChannelSpec)} - {"unit", "doc"}
    for name, change in (overrides or {}).items():
        if name not in specs:
            raise ValueError(f"unknown sensor channel {name!r}; known: {', '.join(specs)}")
        if not isinstance(change, dict) or not set(change) <= allowed:
            raise ValueError(
                f"sensor_params[{name!r}] must be a dict with keys among {sorted(allowed)}"
            )
        specs[name] = replace(specs[name], **{k: float(v) for k, v in change.items()})
    return {
        n: replace(s, noise_std=s.noise_std * noise_scale) for n, s in specs.items()
    }


def as_dict(obj) -> dict:
    """Plain-dict view of a parameter dataclass (for metadata files)."""
    return asdict(obj)
