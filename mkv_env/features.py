"""Sensor features for the linear eigenspace policy.

The projector is linear, so what it can do depends on what it sees: a jam shows as a drive current
that *stays* high, or a bump that happened a moment ago. :class:`FeatureSpec` describes a feature
vector built from raw sensor observations; :class:`FeatureBuilder` computes it two ways that agree
exactly (bit for bit):

- :meth:`FeatureBuilder.transform`: a whole recording at once, given observations, the actions
  taken and episode-start flags;
- :meth:`FeatureBuilder.reset` / :meth:`FeatureBuilder.step`: one observation at a time, at run
  time.

Feature layout, in this order (each block only when enabled):

=====================  ==============================  ==========================================
block                  names                           value at time t
=====================  ==============================  ==========================================
current observation    ``"<ch>[t]"``                   ``obs[t, ch]`` for ``ch`` in ``channels``
history, lag j=1..k    ``"<ch>[t-j]"``                 ``obs[t-j, ch]`` for ``history_channels``
decaying traces        ``"<ch>~<decay>"``              ``tr[t] = decay*tr[t-1] + (1-decay)*obs[t]``
previous command       ``"<act>[t-1]"`` (signed) or    the action taken at ``t-1``
                       ``"<act>[t-1]=<i>"`` (one-hot)
=====================  ==============================  ==========================================

Episode starts reset everything: history before the first step of an episode is padded with that
first observation (``history_pad="edge"``, no fake jump) or zeros (``"zero"``); a trace starts at
the episode's first observation; the previous command at an episode's first step is "none": 0 in
signed mode (the centre "off" value of a 3-valued command) and all zeros in one-hot mode.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from mkv_env.actions import ACTION_NAMES, ACTION_NVEC

__all__ = ["FeatureSpec", "FeatureBuilder", "OnlineFeatures"]

PREV_ACTION_MODES = ("none", "signed", "onehot")
#: Longest history window and most trace decays a spec accepts (a feature vector of thousands of
#: columns is a typo, and the fit refuses more than 10,000 columns anyway).
MAX_HISTORY = 1000
MAX_TRACES = 16
HISTORY_PADS = ("edge", "zero")
SPEC_VERSION = 1


def _names_tuple(value, what):
    if isinstance(value, str):
        raise ValueError(f"{what} must be a sequence of names, not the string {value!r}")
    return tuple(str(v) for v in value)


@dataclass(frozen=True)
class FeatureSpec:
    """What goes into the feature vector. Immutable; JSON-able via :meth:`to_dict`.

    Parameters
    ----------
    obs_names : sequence of str
        Names of the raw observation channels, in observation order
        (``env.unwrapped.sensor_names``).
    channels : sequence of str or None
        Channels used as the current observation; ``None`` = all, ``()`` = none.
    history : int
        Number ``k >= 0`` of previous observations stacked (lags 1..k).
    history_channels : sequence of str or None
        Channels stacked in the history; ``None`` = same as ``channels``.
    history_pad : {"edge", "zero"}
        Value of lags reaching before an episode start: that episode's first observation, or 0.
    trace_decays : sequence of float
        Decay factors in ``[0, 1)`` of exponential moving averages (one trace block per factor).
    trace_channels : sequence of str or None
        Channels that get traces; ``None`` = same as ``channels``.
    prev_action : {"none", "signed", "onehot"}
        Whether and how to include the previous command. Signed maps action index ``a`` of an
        ``n``-valued command to ``a - (n - 1) / 2`` (reverse/off/forward -> -1/0/+1).
    action_nvec : sequence of int
        Number of values of each command (``MultiDiscrete.nvec``), e.g. ``(3, 3)``.
    action_names : sequence of str
        Names of the commands, e.g. ``("drive", "steer")``.
    """

    obs_names: tuple
    channels: tuple | None = None
    history: int = 0
    history_channels: tuple | None = None
    history_pad: str = "edge"
    trace_decays: tuple = ()
    trace_channels: tuple | None = None
    prev_action: str = "none"
    action_nvec: tuple = ACTION_NVEC
    action_names: tuple = ACTION_NAMES
    _version: int = field(default=SPEC_VERSION, repr=False)

    def __post_init__(self):
        set_ = object.__setattr__  # frozen dataclass: normalise fields once, here
        obs_names = _names_tuple(self.obs_names, "obs_names")
        if len(set(obs_names)) != len(obs_names) or not obs_names:
            raise ValueError(f"obs_names must be non-empty and unique; got {obs_names}")
        set_(self, "obs_names", obs_names)
        channels = obs_names if self.channels is None else _names_tuple(self.channels, "channels")
        set_(self, "channels", channels)
        for attr in ("history_channels", "trace_channels"):
            value = getattr(self, attr)
            set_(self, attr, channels if value is None else _names_tuple(value, attr))
        for attr in ("channels", "history_channels", "trace_channels"):
            unknown = [c for c in getattr(self, attr) if c not in obs_names]
            if unknown:
                raise ValueError(f"{attr} has unknown channel(s) {unknown}; valid channels are "
                                 f"{list(obs_names)}")
        if (isinstance(self.history, bool) or int(self.history) != self.history
                or not 0 <= self.history <= MAX_HISTORY):
            raise ValueError(f"history must be an int in [0, {MAX_HISTORY}]; got "
                             f"{self.history!r}")
        set_(self, "history", int(self.history))
        if self.history_pad not in HISTORY_PADS:
            raise ValueError(f"history_pad must be one of {HISTORY_PADS}; got {self.history_pad!r}")
        decays = tuple(float(d) for d in self.trace_decays)
        if len(decays) > MAX_TRACES:
            raise ValueError(f"at most {MAX_TRACES} trace decays; got {len(decays)}")
        bad = [d for d in decays if not 0 <= d < 1]
        if bad:
            raise ValueError(f"trace_decays must be in [0, 1); got {bad}")
        set_(self, "trace_decays", decays)
        if self.prev_action not in PREV_ACTION_MODES:
            raise ValueError(f"prev_action must be one of {PREV_ACTION_MODES}; "
                             f"got {self.prev_action!r}")
        nvec = tuple(int(v) for v in self.action_nvec)
        names = _names_tuple(self.action_names, "action_names")
        if len(nvec) != len(names) or any(v < 1 for v in nvec):
            raise ValueError(f"action_nvec {nvec} and action_names {names} must have the same "
                             f"length and positive entries")
        set_(self, "action_nvec", nvec)
        set_(self, "action_names", names)
        if self._version != SPEC_VERSION:
            raise ValueError(f"feature spec version {self._version} is not supported "
                             f"(this code reads version {SPEC_VERSION})")

    # -------------------------------------------------------------------- layout
    @property
    def feature_names(self):
        """List of output feature names, in output column order."""
        names = [f"{c}[t]" for c in self.channels]
        for lag in range(1, self.history + 1):
            names += [f"{c}[t-{lag}]" for c in self.history_channels]
        for d in self.trace_decays:
            names += [f"{c}~{d}" for c in self.trace_channels]
        if self.prev_action == "signed":
            names += [f"{a}[t-1]" for a in self.action_names]
        elif self.prev_action == "onehot":
            for a, n in zip(self.action_names, self.action_nvec, strict=True):
                names += [f"{a}[t-1]={i}" for i in range(n)]
        return names

    @property
    def n_features(self):
        """Length of the feature vector (counted, not built: cheap for any spec)."""
        n = len(self.channels) + self.history * len(self.history_channels)
        n += len(self.trace_decays) * len(self.trace_channels)
        if self.prev_action == "signed":
            n += len(self.action_names)
        elif self.prev_action == "onehot":
            n += sum(self.action_nvec)
        return n

    def _index(self, names):
        pos = {n: i for i, n in enumerate(self.obs_names)}
        return np.array([pos[n] for n in names], dtype=np.intp)

    # -------------------------------------------------------------------- serialisation
    def to_dict(self):
        """Plain JSON-able dict (lists, str, int, float) that :meth:`from_dict` reads back."""
        out = asdict(self)
        out["version"] = out.pop("_version")
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}

    @classmethod
    def from_dict(cls, data):
        """Inverse of :meth:`to_dict`; refuses unknown keys and other versions."""
        data = dict(data)
        version = data.pop("version", SPEC_VERSION)
        known = {f for f in cls.__dataclass_fields__ if not f.startswith("_")}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown feature spec key(s) {sorted(unknown)}; "
                             f"valid keys are {sorted(known)}")
        return cls(**data, _version=version)


class FeatureBuilder:
    """Compute :class:`FeatureSpec` features for a recording (batch) or step by step (online).

    Parameters
    ----------
    spec : FeatureSpec

    Examples
    --------
    >>> spec = FeatureSpec(obs_names=["a", "b"], history=1, trace_decays=[0.5],
    ...                    prev_action="signed", action_nvec=[3], action_names=["drive"])
    >>> fb = FeatureBuilder(spec)
    >>> fb.feature_names
    ['a[t]', 'b[t]', 'a[t-1]', 'b[t-1]', 'a~0.5', 'b~0.5', 'drive[t-1]']
    >>> fb.reset()
    >>> fb.step([1.0, 2.0]).tolist()
    [1.0, 2.0, 1.0, 2.0, 1.0, 2.0, 0.0]
    >>> fb.step([3.0, 2.0], prev_action=[2]).tolist()
    [3.0, 2.0, 1.0, 2.0, 2.0, 2.0, 1.0]
    """

    def __init__(self, spec):
        if not isinstance(spec, FeatureSpec):
            raise TypeError(f"spec must be a FeatureSpec; got {type(spec).__name__}")
        self.spec = spec
        self._cur = spec._index(spec.channels)
        self._hist = spec._index(spec.history_channels)
        self._trace = spec._index(spec.trace_channels)
        self._decays = np.array(spec.trace_decays, dtype=np.float64)
        self._one_minus = 1.0 - self._decays
        # per trace entry (decay-major, channel-minor), shared by both paths
        self._d_rep = np.repeat(self._decays, len(self._trace))
        self._om_rep = np.repeat(self._one_minus, len(self._trace))
        self._n_obs = len(spec.obs_names)
        self._n_act = len(spec.action_nvec)
        self._centre = (np.array(spec.action_nvec, dtype=np.float64) - 1.0) / 2.0
        self._offsets = np.concatenate([[0], np.cumsum(spec.action_nvec)[:-1]]).astype(np.intp)
        self._started = False

    @property
    def feature_names(self):
        """List of output feature names (see :class:`FeatureSpec`)."""
        return self.spec.feature_names

    @property
    def n_features(self):
        return self.spec.n_features

    def to_dict(self):
        """JSON-able dict of the spec (the builder's run-time state is not saved)."""
        return self.spec.to_dict()

    @classmethod
    def from_dict(cls, data):
        return cls(FeatureSpec.from_dict(data))

    # -------------------------------------------------------------------- checks
    def _check_obs(self, obs, batch):
        obs = np.asarray(obs, dtype=np.float64)
        want = 2 if batch else 1
        if obs.ndim != want or obs.shape[-1] != self._n_obs:
            shape = "(T, n_obs)" if batch else "(n_obs,)"
            raise ValueError(f"observations must have shape {shape} with n_obs={self._n_obs}; "
                             f"got {obs.shape}")
        return obs

    def _check_actions(self, actions, n_rows):
        act = np.asarray(actions)
        if act.ndim == 1 and self._n_act == 1 and n_rows is not None:
            act = act[:, None]
        want = (n_rows, self._n_act) if n_rows is not None else (self._n_act,)
        if act.shape != want:
            raise ValueError(f"actions must have shape {want}; got {act.shape}")
        if not np.issubdtype(act.dtype, np.integer):
            if not np.all(act == np.round(act)):
                raise ValueError("actions must be integer action indices")
            act = act.astype(np.int64)
        nvec = np.array(self.spec.action_nvec)
        if np.any(act < 0) or np.any(act >= nvec):
            raise ValueError(f"action indices must be in [0, nvec) with nvec={list(nvec)}")
        return act

    def _encode_actions(self, act, valid):
        """Previous-command block for action rows ``act`` (m, n_act); rows where ~valid -> none."""
        m = act.shape[0]
        if self.spec.prev_action == "signed":
            out = act.astype(np.float64) - self._centre
            out[~valid] = 0.0
            return out
        out = np.zeros((m, int(sum(self.spec.action_nvec))))
        rows = np.nonzero(valid)[0]
        for j in range(self._n_act):
            out[rows, self._offsets[j] + act[rows, j]] = 1.0
        return out

    # -------------------------------------------------------------------- batch
    def transform(self, observations, actions=None, episode_start=None):
        """Features of a whole recording.

        Parameters
        ----------
        observations : array-like of shape (T, n_obs)
            Raw observations, in time order.
        actions : array-like of int, shape (T, n_act), or None
            ``actions[t]`` is the command sent after observing ``observations[t]`` (so row ``t``'s
            previous command is ``actions[t-1]``). Required when ``prev_action != "none"``.
        episode_start : array-like of bool, shape (T,), or None
            True where a new episode begins (row 0 always does). ``None``: one episode.

        Returns
        -------
        features : ndarray of shape (T, n_features)
            Identical to calling :meth:`reset` then :meth:`step` row by row (resetting at each
            episode start, with ``prev_action = actions[t-1]``).
        """
        spec = self.spec
        obs = self._check_obs(observations, batch=True)
        t_len = obs.shape[0]
        if episode_start is None:
            start = np.zeros(t_len, dtype=bool)
        else:
            start = np.asarray(episode_start, dtype=bool).copy()
            if start.shape != (t_len,):
                raise ValueError(f"episode_start must have shape ({t_len},); got {start.shape}")
        if t_len:
            start[0] = True
        idx = np.arange(t_len)
        first = np.maximum.accumulate(np.where(start, idx, 0))  # row of this episode's first step

        blocks = [obs[:, self._cur]]
        if spec.history:
            h = obs[:, self._hist]
            for lag in range(1, spec.history + 1):
                src = idx - lag
                before = src < first
                lagged = h[np.where(before, first, src)]
                if spec.history_pad == "zero":
                    lagged[before] = 0.0
                blocks.append(lagged)
        if self._decays.size:
            blocks.append(self._traces(obs[:, self._trace], start))
        if spec.prev_action != "none":
            if actions is None:
                raise ValueError(f"actions are required with prev_action={spec.prev_action!r}")
            act = self._check_actions(actions, t_len)
            prev = np.roll(act, 1, axis=0)
            blocks.append(self._encode_actions(prev, ~start))
        return np.concatenate(blocks, axis=1) if blocks else np.empty((t_len, 0))

    def _traces(self, x, start):
        """Exponential moving averages, one block per decay: (T, n_decays * n_channels)."""
        # One recurrence over time for all decays and channels at once, written with exactly the
        # same floating-point operations as step(), which is what makes both paths bit-identical.
        t_len = x.shape[0]
        d, om = self._d_rep, self._om_rep
        xs = np.tile(x, (1, self._decays.size))
        out = np.empty_like(xs)
        tr = xs[0] if t_len else None
        for t in range(t_len):
            tr = xs[t].copy() if start[t] else d * tr + om * xs[t]
            out[t] = tr
        return out

    # -------------------------------------------------------------------- online
    def reset(self):
        """Forget the past: the next :meth:`step` is the first of an episode."""
        self._started = False

    def step(self, obs, prev_action=None):
        """Features for one observation at run time.

        Parameters
        ----------
        obs : array-like of shape (n_obs,)
        prev_action : array-like of int, shape (n_act,), or None
            The command sent at the previous step. Ignored at the first step after
            :meth:`reset` (an episode's first step has no previous command, as in
            :meth:`transform`); ``None`` later means "none" (encoded as at an episode start).

        Returns
        -------
        features : ndarray of shape (n_features,)
        """
        spec = self.spec
        x = self._check_obs(obs, batch=False)
        first = not self._started
        parts = [x[self._cur]]
        if spec.history:
            h = x[self._hist]
            if first:
                pad = h if spec.history_pad == "edge" else np.zeros_like(h)
                self._past = [pad.copy() for _ in range(spec.history)]
            parts.extend(self._past)
            self._past = [h.copy()] + self._past[:-1]
        if self._decays.size:
            xs = np.tile(x[self._trace], self._decays.size)
            if first:
                self._tr = xs.copy()
            else:
                self._tr = self._d_rep * self._tr + self._om_rep * xs
            parts.append(self._tr)
        if spec.prev_action != "none":
            valid = not first and prev_action is not None
            act = (self._check_actions(prev_action, None)[None, :] if valid
                   else np.zeros((1, self._n_act), dtype=np.int64))
            parts.append(self._encode_actions(act, np.array([valid]))[0])
        self._started = True
        return np.concatenate(parts) if parts else np.empty(0)


class OnlineFeatures:
    """Run-time features for a policy serving one env or a batch of envs (SB3's ``predict``
    contract): one :class:`FeatureBuilder` (history, traces) and one previous command per env
    index, each reset when its ``episode_start`` flag is set.

    ``step(observations, episode_start)`` returns one feature row per env; after the policy has
    chosen its actions it calls ``set_previous(actions)`` so they enter the next step's features.
    """

    def __init__(self, spec):
        self.spec = spec
        self.n_obs = len(spec.obs_names)
        self._builders: list[FeatureBuilder] = []
        self._prev: list = []

    def reset(self) -> None:
        """Start a new episode in every env."""
        for b in self._builders:
            b.reset()
        self._prev = [None] * len(self._builders)

    def as_batch(self, observation, who: str = "the policy") -> tuple[np.ndarray, bool]:
        """``(observations of shape (n_envs, n_obs), single)`` from one observation or a batch;
        ValueError (one line) for any other shape."""
        obs = np.asarray(observation, dtype=np.float64)
        if obs.ndim == 1 and obs.shape[0] == self.n_obs:
            return obs[None, :], True
        if obs.ndim == 2 and obs.shape[1] == self.n_obs and obs.shape[0] >= 1:
            return obs, False
        raise ValueError(f"{who} takes one observation of shape ({self.n_obs},) or a batch of "
                         f"shape (n_envs, {self.n_obs}); got shape {obs.shape}")

    def step(self, observations, episode_start=None) -> list[np.ndarray]:
        """Features of each env's observation, shape (n_features,) each, in env order.

        ``observations`` has shape (n_envs, n_obs); ``episode_start`` is None, a bool, or one
        bool per env (True starts that env's episode: no history, no previous command).
        """
        n = len(observations)
        while len(self._builders) < n:
            self._builders.append(FeatureBuilder(self.spec))
            self._prev.append(None)
        starts = (np.zeros(n, dtype=bool) if episode_start is None
                  else np.broadcast_to(np.asarray(episode_start, dtype=bool).reshape(-1), (n,)))
        out = []
        for i in range(n):
            if starts[i]:
                self._builders[i].reset()
                self._prev[i] = None
            out.append(self._builders[i].step(observations[i], self._prev[i]))
        return out

    def set_previous(self, actions) -> None:
        """The commands just sent, shape (n_envs, n_act), for the next step's features."""
        for i, a in enumerate(actions):
            self._prev[i] = a


def default_feature_spec(obs_names, action_nvec=ACTION_NVEC, action_names=ACTION_NAMES):
    """The feature set the ``mkv fit`` / ``mkv train-bc`` defaults use (see docs/sfm.md for the
    feature-set study that chose it): every channel now, decaying traces of all channels, and the
    previous command (signed).
    """
    return FeatureSpec(obs_names=tuple(obs_names), trace_decays=(0.5, 0.8),
                       prev_action="signed", action_nvec=tuple(int(n) for n in action_nvec),
                       action_names=tuple(action_names))


__all__ = [*__all__, "default_feature_spec"]
