"""Physical parameters of the MK-V robot and its world, with units.

Body frame: x forward, y to the left, origin at the chassis centre; angles counter-clockwise.
Every number here is a documented default that a user can override through ``gymnasium.make``
kwargs (see :class:`mkv_env.envs.MKVEnv`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

GRAVITY_MPS2 = 9.81


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def _real(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _in(name: str, v, low: float, high: float, *, low_open: bool = False,
        unit: str = "") -> None:
    """ValueError unless ``low (<|<=) v <= high`` for a finite real ``v``."""
    ok = _real(v) and (v > low if low_open else v >= low) and v <= high
    bracket = "(" if low_open else "["
    _require(ok, f"{name} must be a number in {bracket}{low:g}, {high:g}]{unit}, got {v!r}")


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

    def __post_init__(self) -> None:
        _in("supply_v", self.supply_v, 0.5, 48.0, unit=" V")
        _in("resistance_ohm", self.resistance_ohm, 0.1, 1e4, unit=" ohm")
        _in("k_nm_per_a", self.k_nm_per_a, 1e-3, 100.0, unit=" N m/A")
        _in("viscous_nms", self.viscous_nms, 0.0, 10.0, unit=" N m s/rad")
        _in("inertia_kgm2", self.inertia_kgm2, 1e-6, 10.0, unit=" kg m^2")

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

    def __post_init__(self) -> None:
        """Every value physically meaningful (a negative mass or NaN friction would abort
        Chipmunk, the C physics engine, and take the interpreter with it)."""
        _in("mass_kg", self.mass_kg, 0.1, 100.0, unit=" kg")
        _in("length_m", self.length_m, 0.05, 5.0, unit=" m")
        _in("width_m", self.width_m, 0.05, 5.0, unit=" m")
        _in("bumper_gap_m", self.bumper_gap_m, 0.0, 0.2, unit=" m")
        half = self.length_m / 2
        _in("drive_x_m", self.drive_x_m, -half, half, unit=" m (inside the chassis)")
        _in("steer_x_m", self.steer_x_m, -half, half, unit=" m (inside the chassis)")
        _require(self.steer_x_m - self.drive_x_m > 0.01,
                 f"steer_x_m ({self.steer_x_m!r}) must lie ahead of drive_x_m "
                 f"({self.drive_x_m!r})")
        _require(isinstance(self.caster_xy_m, (tuple, list)) and len(self.caster_xy_m) == 2
                 and all(_real(v) for v in self.caster_xy_m),
                 f"caster_xy_m must be two finite numbers [m], got {self.caster_xy_m!r}")
        _in("drive_wheel_radius_m", self.drive_wheel_radius_m, 0.005, 0.5, unit=" m")
        _in("steer_wheel_radius_m", self.steer_wheel_radius_m, 0.005, 0.5, unit=" m")
        _in("drive_load_fraction", self.drive_load_fraction, 0.05, 1.0)
        _in("steer_load_fraction", self.steer_load_fraction, 0.05, 1.0)
        _require(self.drive_load_fraction + self.steer_load_fraction <= 1.0,
                 "drive_load_fraction + steer_load_fraction must be at most 1 (the caster "
                 f"carries the rest), got {self.drive_load_fraction + self.steer_load_fraction:g}")
        _in("tire_friction", self.tire_friction, 0.01, 5.0)
        _in("steer_limit_rad", self.steer_limit_rad, 0.01, 1.5, unit=" rad")
        _in("steer_coulomb_nm", self.steer_coulomb_nm, 0.0, 10.0, unit=" N m")
        _in("chassis_friction", self.chassis_friction, 0.0, 5.0)
        for name in ("drive_motor", "steer_motor"):
            _require(isinstance(getattr(self, name), DCMotor),
                     f"{name} must be a DCMotor (or a dict of its fields)")

    def replace(self, **changes) -> RobotParams:
        return replace(self, **changes)

    @classmethod
    def from_overrides(cls, overrides) -> RobotParams:
        """Defaults with ``overrides`` (a dict of field values; motors as dicts of
        :class:`DCMotor` fields) applied; ValueError with one line for anything else."""
        if overrides is None:
            return cls()
        _require(isinstance(overrides, dict),
                 f"robot_params must be a dict of RobotParams fields, got {overrides!r}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"unknown robot_params field {unknown[0]!r}; known: "
                             f"{', '.join(sorted(known))}")
        changes = dict(overrides)
        base = cls()
        for name in ("drive_motor", "steer_motor"):
            if isinstance(changes.get(name), dict):
                motor = changes[name]
                motor_known = {f.name for f in fields(DCMotor)}
                bad = sorted(set(motor) - motor_known)
                if bad:
                    raise ValueError(f"unknown {name} field {bad[0]!r}; known: "
                                     f"{', '.join(sorted(motor_known))}")
                changes[name] = replace(getattr(base, name), **motor)
        if isinstance(changes.get("caster_xy_m"), list):
            changes["caster_xy_m"] = tuple(changes["caster_xy_m"])
        return replace(base, **changes)


#: Largest magnitude a reading, its range, noise or bias may have (the datasets refuse larger
#: readings as damaged; mkv_env.dataset.MAX_ABS_READING).
MAX_READING = 1e6
#: Smallest non-zero quantisation step (a subnormal step overflows 1/step).
MIN_QUANTUM = 1e-9


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

    def __post_init__(self) -> None:
        for name in ("low", "high", "noise_std", "quantum", "bias"):
            _require(_real(getattr(self, name)),
                     f"sensor {name} must be a finite number, got {getattr(self, name)!r}")
        _in("sensor low", self.low, -MAX_READING, MAX_READING)
        _in("sensor high", self.high, -MAX_READING, MAX_READING)
        _require(self.low < self.high, f"sensor low ({self.low!r}) must be below high "
                                       f"({self.high!r})")
        _in("sensor noise_std", self.noise_std, 0.0, MAX_READING)
        _in("sensor quantum", self.quantum, 0.0, self.high - self.low)
        _require(self.quantum == 0 or self.quantum >= MIN_QUANTUM,
                 f"sensor quantum must be 0 (none) or at least {MIN_QUANTUM:g}, got "
                 f"{self.quantum!r}")
        _in("sensor bias", self.bias, -MAX_READING, MAX_READING)


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


#: The sensor channels in observation order: the one tuple every module reads.
SENSOR_NAMES: tuple[str, ...] = tuple(DEFAULT_CHANNELS)


def channel_specs(overrides=None, noise_scale: float = 1.0) -> dict[str, ChannelSpec]:
    """Default channels with per-channel overrides and a global noise multiplier.

    ``overrides`` maps a channel name to a dict of :class:`ChannelSpec` fields, e.g.
    ``{"compass": {"bias": 0.1, "noise_std": 0.0}}``.
    """
    if not (_real(noise_scale) and noise_scale >= 0):
        raise ValueError(f"sensor_noise must be a finite number >= 0, got {noise_scale!r}")
    if overrides is not None and not isinstance(overrides, dict):
        raise ValueError("sensor_params must map channel names to dicts of ChannelSpec fields, "
                         f"e.g. {{\"compass\": {{\"bias\": 0.1}}}}; got {overrides!r}")
    specs = dict(DEFAULT_CHANNELS)
    allowed = {f.name for f in fields(ChannelSpec)} - {"unit", "doc"}
    for name, change in (overrides or {}).items():
        if name not in specs:
            raise ValueError(f"unknown sensor channel {name!r}; known: {', '.join(specs)}")
        if not isinstance(change, dict) or not set(change) <= allowed:
            raise ValueError(
                f"sensor_params[{name!r}] must be a dict with keys among {sorted(allowed)}"
            )
        bad = [k for k, v in change.items() if not _real(v)]
        if bad:
            raise ValueError(f"sensor_params[{name!r}][{bad[0]!r}] must be a finite number, "
                             f"got {change[bad[0]]!r}")
        specs[name] = replace(specs[name], **{k: float(v) for k, v in change.items()})
    return {
        n: replace(s, noise_std=s.noise_std * noise_scale) for n, s in specs.items()
    }


def as_dict(obj) -> dict:
    """Plain-dict view of a parameter dataclass (for metadata files)."""
    return asdict(obj)
