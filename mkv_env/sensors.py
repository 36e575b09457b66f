"""The MK-V's sensors: what the learner sees, made from the world's true state.

Each channel reads ``truth + bias + noise``, then is quantised to its ADC step and clipped to its
documented range (:data:`mkv_env.params.DEFAULT_CHANNELS`). Noise comes from ``np_random`` in
blocks of rows, so it costs one array add per step and stays a pure function of the seed.
"""

from __future__ import annotations

import math

import numpy as np

from mkv_env.params import ChannelSpec
from mkv_env.world import World

_NOISE_BLOCK = 256
_FINE = 2.0**-30  # "no quantisation": a power of two keeps round(x / q) * q exact to 1e-9
_TWO_PI = 2.0 * math.pi

TICKS_PER_REV = 128
"""Resolution of both wheel encoders [ticks per wheel revolution]."""
BATTERY_NOMINAL_V = 7.2
BATTERY_INTERNAL_OHM = 0.8


class SensorSuite:
    """Turns a :class:`World` into an observation vector, one control period at a time.

    Args:
        specs: channel name -> :class:`ChannelSpec`, in observation order.
    """

    def __init__(self, specs: dict[str, ChannelSpec]):
        expected = (
            "drive_ticks", "roller_ticks", "steer_angle", "compass", "bump_front_left",
            "bump_front_right", "bump_rear", "drive_current", "steer_current", "battery",
        )
        if tuple(specs) != expected:
            raise ValueError(f"sensor channels must be {expected}, got {tuple(specs)}")
        self.specs = specs
        self.names = list(specs)
        self.low = np.array([s.low for s in specs.values()], dtype=np.float64)
        self.high = np.array([s.high for s in specs.values()], dtype=np.float64)
        self._std = np.array([s.noise_std for s in specs.values()])
        self._bias = np.array([s.bias for s in specs.values()])
        q = np.array([s.quantum for s in specs.values()])
        self._q = np.where(q > 0, q, _FINE)
        self._inv_q = 1.0 / self._q
        self._tick_angle = _TWO_PI / TICKS_PER_REV
        self._rng = None
        self._noise = np.zeros((0, len(specs)))
        self._row = 0
        self._last_ticks = (0, 0)

    def reset(self, rng: np.random.Generator, world: World) -> None:
        """Start a new episode: new noise stream, encoders zeroed at the current wheel angles."""
        self._rng = rng
        self._row = _NOISE_BLOCK
        self._last_ticks = self._ticks(world)

    def _ticks(self, world: World) -> tuple[int, int]:
        st = world.robot.state
        return (math.floor(st.drive_angle / self._tick_angle),
                math.floor(st.roller_angle / self._tick_angle))

    def read(self, world: World) -> np.ndarray:
        """One observation, float32 of shape (n_channels,)."""
        st = world.robot.state
        ticks = self._ticks(world)
        d_ticks = ticks[0] - self._last_ticks[0]
        r_ticks = ticks[1] - self._last_ticks[1]
        self._last_ticks = ticks
        c = world.contacts
        i_d, i_s = st.drive_current, st.steer_current
        heading = world.robot.body.angle
        truth = np.array((
            d_ticks, r_ticks, st.steer, heading,
            c[2] > 0, c[3] > 0, c[4] > 0,
            i_d, i_s, BATTERY_NOMINAL_V - BATTERY_INTERNAL_OHM * (abs(i_d) + abs(i_s)),
        ), dtype=np.float64)
        if self._row >= _NOISE_BLOCK:
            self._noise = self._rng.standard_normal((_NOISE_BLOCK, len(self.names)))
            self._noise *= self._std
            self._noise += self._bias
            self._row = 0
        truth += self._noise[self._row]
        self._row += 1
        truth[3] = (truth[3] + math.pi) % _TWO_PI - math.pi
        np.round(truth * self._inv_q, out=truth)
        truth *= self._q
        np.maximum(truth, self.low, out=truth)
        np.minimum(truth, self.high, out=truth)
        return truth.astype(np.float32)
