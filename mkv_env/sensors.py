"""The MK-V's sensors: what the learner sees, made from the world's true state.

Each channel reads ``truth + bias + noise``, then is quantised to its ADC step and clipped to its
documented range (:data:`mkv_env.params.DEFAULT_CHANNELS`). Noise comes from ``np_random`` in
blocks of rows, so it costs one array add per step and stays a pure function of the seed.
"""

from __future__ import annotations

import math

import numpy as np

from mkv_env.params import SENSOR_NAMES, ChannelSpec
from mkv_env.robot import _fastsim
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
        if tuple(specs) != SENSOR_NAMES:
            raise ValueError(f"sensor channels must be {SENSOR_NAMES}, got {tuple(specs)}")
        self.specs = specs
        self.names = list(specs)
        self.low = np.array([s.low for s in specs.values()], dtype=np.float64)
        self.high = np.array([s.high for s in specs.values()], dtype=np.float64)
        self._std = np.array([s.noise_std for s in specs.values()])
        self._bias = np.array([s.bias for s in specs.values()])
        q = np.array([s.quantum for s in specs.values()])
        self._q = np.where(q > 0, q, _FINE)
        self._inv_q = 1.0 / self._q
        self._q_l, self._inv_q_l = self._q.tolist(), self._inv_q.tolist()
        self._low_l, self._high_l = self.low.tolist(), self.high.tolist()
        self._tick_angle = _TWO_PI / TICKS_PER_REV
        self._rng = None
        self._block: np.ndarray | None = None  # the current noise block (rows x channels)
        self._noise: list[list[float]] = []
        self._row = 0
        self._last_ticks = (0, 0)
        self._out = np.zeros(len(self.names), dtype=np.float32)

    def reset(self, rng: np.random.Generator, world: World) -> None:
        """Start a new episode: new noise stream, encoders zeroed at the current wheel angles."""
        self._rng = rng
        self._row = _NOISE_BLOCK
        self._last_ticks = self._ticks(world)

    def restart(self, rng: np.random.Generator) -> None:
        """Start a new episode whose encoders read zero now (a world built by the compiled
        kernel's reset: its wheel angles start at zero): :meth:`reset` without a world."""
        self._rng = rng
        self._row = _NOISE_BLOCK
        self._last_ticks = (0, 0)

    def to_state(self) -> dict:
        """The episode state another owner continues from (an env's compiled step kernel:
        :func:`mkv_env.kernel.push`): the noise ``row`` reached in the current noise ``block``
        (float64, rows x channels; None before the first draw), the encoders' ``last_ticks``,
        and the noise source: the episode's generator ``rng`` and the channels' ``std`` and
        ``bias``."""
        return {"row": self._row, "block": self._block, "last_ticks": self._last_ticks,
                "rng": self._rng, "std": self._std, "bias": self._bias}

    def load_state(self, state: dict) -> None:
        """Take the noise ``row``, ``block`` (float64 bytes or array, rows x channels) and
        encoder ``last_ticks`` another owner of this suite's state has reached (the compiled step
        kernel's slot: :func:`mkv_env.kernel.pull`); the block is rebuilt only when it changed.
        The noise source stays this suite's."""
        row, block = state["row"], state["block"]
        raw = block.tobytes() if isinstance(block, np.ndarray) else block
        if row != self._row or self._block is None or self._block.tobytes() != raw:
            self._block = np.frombuffer(raw, dtype=np.float64).reshape(_NOISE_BLOCK, -1).copy()
            self._noise = self._block.tolist()
        self._row = row
        self._last_ticks = tuple(state["last_ticks"])

    def draw_block(self) -> np.ndarray:
        """The next block of noise rows (bias + std * standard normal), drawn from the episode's
        generator; kept as the current block. (The compiled step kernel asks for blocks through
        this too, so the draws are the same.)"""
        block = self._rng.standard_normal((_NOISE_BLOCK, len(self.names)))
        block *= self._std
        block += self._bias
        self._block = block
        return block

    def _ticks(self, world: World) -> tuple[int, int]:
        st = world.robot.state
        return (math.floor(st.drive_angle / self._tick_angle),
                math.floor(st.roller_angle / self._tick_angle))

    def read(self, world: World) -> np.ndarray:
        """One observation, float32 of shape (n_channels,)."""
        st = world.robot.state
        tick = self._tick_angle
        dt_, rt_ = math.floor(st.drive_angle / tick), math.floor(st.roller_angle / tick)
        d0, r0 = self._last_ticks
        self._last_ticks = (dt_, rt_)
        c = world.contacts
        i_d, i_s = st.drive_current, st.steer_current
        if self._row >= _NOISE_BLOCK:
            # plain floats: per-step work stays in Python scalars
            self._noise = self.draw_block().tolist()
            self._row = 0
        nz = self._noise[self._row]
        self._row += 1
        heading = (world.robot.angle() + nz[3] + math.pi) % _TWO_PI - math.pi
        truth = (
            dt_ - d0 + nz[0], rt_ - r0 + nz[1], st.steer + nz[2], heading,
            (c[2] > 0) + nz[4], (c[3] > 0) + nz[5], (c[4] > 0) + nz[6],
            i_d + nz[7], i_s + nz[8],
            BATTERY_NOMINAL_V - BATTERY_INTERNAL_OHM * (abs(i_d) + abs(i_s)) + nz[9],
        )
        if _fastsim is not None:  # the same arithmetic compiled (mkv_env/_native/)
            _fastsim.quantize(truth, self._inv_q, self._q, self.low, self.high, self._out)
            return self._out.copy()
        return np.array(
            [min(max(round(x * iq) * q, lo), hi)
             for x, iq, q, lo, hi in zip(truth, self._inv_q_l, self._q_l, self._low_l,
                                         self._high_l, strict=False)],
            dtype=np.float32,
        )
