"""The shape-from-motion policy: features -> eigenspace projector -> three-valued motor commands.

Training (the paper's section 9, docs/design.md section 4): every time step of the teacher's runs
becomes one row ``[sensor features, motor commands]``; :class:`~sfm_learn.eigenspace.projector.
EigenspaceProjector` standardises the columns, takes the SVD and keeps the leading eigenvectors.
At run time only the sensor part is known: the projector solves the eigenspace coefficients from
it and reconstructs the commands, continuous values on the signed scale (reverse/left = -1,
off = 0, forward/right = +1). Each is then quantised back to reverse / off / forward with two
thresholds ``lo < hi`` per command::

    command = reverse (index 0) if value < lo,  off (1) if lo <= value <= hi,  forward (2) if > hi

``thresholds="fixed"`` uses the midpoints ``lo = -0.5, hi = +0.5``. ``thresholds="learned"`` (the
default) picks, per command, the pair that maximises the *balanced* accuracy (mean per-class
recall) on the training rows, so a rare class (reverse, steering) is not given up for the frequent
one; both are recorded in the saved model.

Files: ``POLICY.npz`` holds the arrays (projector state, thresholds) and one JSON member with the
metadata: format, feature spec, sensor names, env id, training summary (rows, episodes, rank,
singular values, wall time). Loading checks the format and, given an env, that its sensor names
equal the saved ones.
"""

from __future__ import annotations

import io
import json
import os
import time
import tokenize
import zipfile
import zlib

import numpy as np

from mkv_env.actions import ACTION_NVEC
from mkv_env.features import (
    FeatureBuilder,
    FeatureSpec,
    OnlineFeatures,
    default_feature_spec,
)
from sfm_common.files import atomic_path
from sfm_learn.eigenspace.projector import EigenspaceProjector

__all__ = ["SfMPolicy", "PolicyFileError", "fit_policy", "load_spec", "learn_thresholds",
           "quantise", "FORMAT", "PRESETS", "preset", "fit_columns", "min_fit_rows",
           "check_fit_rows"]

FORMAT = "mkv-sfm-policy"
FORMAT_VERSION = 2  # 2: the complete projector (to_arrays); 1: run-time arrays only
FIXED_THRESHOLDS = (-0.5, 0.5)
_META_MEMBER = "metadata.json"
_V1_ARRAYS = ("mean_", "scale_", "components_", "singular_values_", "coef_", "intercept_")


class PolicyFileError(ValueError):
    """A policy file that is missing, corrupt, of another format or for another sensor layout."""


def quantise(values, thresholds):
    """Map continuous signed commands (n, n_act) or (n_act,) to action indices 0/1/2.

    ``thresholds`` has shape (n_act, 2): ``(lo, hi)`` per command.
    """
    v = np.asarray(values, dtype=np.float64)
    t = np.asarray(thresholds, dtype=np.float64)
    return (v >= t[..., 0]).astype(np.int64) + (v > t[..., 1]).astype(np.int64)


def _balanced_accuracy(pred, true, n_classes=3):
    recalls = [np.mean(pred[true == c] == c) for c in range(n_classes) if np.any(true == c)]
    return float(np.mean(recalls)) if recalls else 0.0


def learn_thresholds(values, actions, n_grid=41):
    """Per command, the ``(lo, hi)`` pair that maximises balanced accuracy on training rows.

    Args:
        values: reconstructed signed commands, shape (n, n_act).
        actions: the teacher's action indices, shape (n, n_act).
        n_grid: candidate thresholds per side (quantiles of the values).
    """
    values = np.asarray(values, dtype=np.float64)
    actions = np.asarray(actions)
    out = np.empty((values.shape[1], 2))
    for j in range(values.shape[1]):
        v, a = values[:, j], actions[:, j]
        cand = np.unique(np.quantile(v, np.linspace(0.0, 1.0, n_grid)))
        cand = np.concatenate([[-np.inf], (cand[:-1] + cand[1:]) / 2, [np.inf]])
        best, best_score = FIXED_THRESHOLDS, -1.0
        for lo in cand:
            for hi in cand[cand >= lo]:
                score = _balanced_accuracy(quantise(v, np.array([lo, hi])), a)
                if score > best_score + 1e-12:
                    best, best_score = (lo, hi), score
        lo, hi = best
        # infinite thresholds (a class never predicted) are stored as large finite numbers
        out[j] = [np.clip(lo, -1e6, 1e6), np.clip(hi, -1e6, 1e6)]
    return out


class SfMPolicy:
    """A fitted shape-from-motion policy with the stable-baselines3 ``predict`` interface.

    Build one with :func:`fit_policy` or :meth:`load`. It is stateful like the teacher (the
    feature builder keeps history, traces and the previous command): ``predict`` with
    ``episode_start=True`` or :meth:`reset` starts a new episode.
    """

    def __init__(self, projector: EigenspaceProjector, feature_spec: FeatureSpec, thresholds,
                 env_id: str | None = None, training: dict | None = None):
        self.projector = projector
        self.feature_spec = feature_spec
        self.builder = FeatureBuilder(feature_spec)
        self.thresholds = np.asarray(thresholds, dtype=np.float64).reshape(-1, 2)
        self.env_id = env_id
        self.training = dict(training or {})
        self.spec = "sfm"
        self._coef = np.ascontiguousarray(projector.coef_)
        self._intercept = projector.intercept_.copy()
        self._online = OnlineFeatures(feature_spec)

    # ------------------------------------------------------------------ properties
    @property
    def sensor_names(self) -> tuple:
        return tuple(self.feature_spec.obs_names)

    @property
    def n_components(self) -> int:
        return int(self.projector.n_components_)

    # ------------------------------------------------------------------ run time
    def reset(self, seed: int | None = None) -> None:
        """Start a new episode in every env (forget history, traces and previous commands)."""
        self._online.reset()

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        """SB3's ``predict``: ``(actions, state)``.

        ``observation`` is one observation, shape (n_obs,), or a batch, shape (n_envs, n_obs),
        one row per env of a vector env; the returned actions are int64 of shape (n_act,) or
        (n_envs, n_act). Each env keeps its own feature state (history, traces, previous
        command); ``episode_start`` (one bool, or one per env) starts that env's episode.
        ``state`` is returned unchanged (the policy keeps its memory itself); ``deterministic``
        is ignored (the policy is deterministic).
        """
        obs, single = self._online.as_batch(observation, "SfMPolicy.predict")
        feats = self._online.step(obs, episode_start)
        actions = np.stack([self.decode(f @ self._coef + self._intercept) for f in feats])
        self._online.set_previous(actions)
        return (actions[0] if single else actions), state

    def batch_values(self, observations, actions, episode_start) -> np.ndarray:
        """Continuous commands for a whole recording, the previous command taken from
        ``actions`` (the teacher's: an open-loop replay, as in the paper's Figure 3)."""
        f = self.builder.transform(observations, actions, episode_start)
        return f @ self._coef + self._intercept

    def batch_predict(self, observations, actions, episode_start) -> np.ndarray:
        """Quantised :meth:`batch_values`: the action indices (n, n_act)."""
        return self.decode(self.batch_values(observations, actions, episode_start))

    @property
    def encoding(self) -> str:
        n_act = len(self.feature_spec.action_nvec)
        return "signed" if self._intercept.shape[-1] == n_act else "onehot"

    def decode(self, values) -> np.ndarray:
        """Reconstructed command columns -> action indices: thresholds on signed values, or the
        largest entry of each one-hot block."""
        if self.encoding == "signed":
            return quantise(values, self.thresholds)
        v = np.asarray(values)
        out, k0 = [], 0
        for k in self.feature_spec.action_nvec:
            out.append(np.argmax(v[..., k0:k0 + k], axis=-1))
            k0 += k
        return np.stack(out, axis=-1).astype(np.int64)

    # ------------------------------------------------------------------ files
    def metadata(self) -> dict:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "env_id": self.env_id,
            "sensor_names": list(self.sensor_names),
            "feature_spec": self.feature_spec.to_dict(),
            "projector": self.projector.get_params(),
            "n_components": self.n_components,
            "n_known": int(self.projector.n_known_),
            "n_samples_seen": float(self.projector.n_samples_seen_),
            "rank_floor": float(self.projector.rank_floor_),
            "noise_variance": float(self.projector.noise_variance_),
            "training": self.training,
        }

    def save(self, path) -> str:
        """Write ``path`` (.npz) atomically; returns the path.

        Members: ``projector.<name>.npy`` (everything :meth:`EigenspaceProjector.to_arrays`
        holds, so the loaded projector is complete, ``partial_fit`` included),
        ``thresholds.npy`` and ``metadata.json``.
        """
        path = os.fspath(path)
        arrays = {f"projector.{k}": v for k, v in self.projector.to_arrays().items()}
        arrays["thresholds"] = self.thresholds
        meta = json.dumps(self.metadata(), indent=2, sort_keys=True, default=_json_default)
        with atomic_path(path, ".npz") as tmp, zipfile.ZipFile(tmp, "w",
                                                               zipfile.ZIP_DEFLATED) as zf:
            for key, a in arrays.items():
                buf = io.BytesIO()
                np.save(buf, np.asarray(a), allow_pickle=False)
                zf.writestr(key + ".npy", buf.getvalue())
            zf.writestr(_META_MEMBER, meta)
        return path

    @classmethod
    def load(cls, path, env=None) -> SfMPolicy:
        """Read a policy file; with ``env``, check its sensor names match.

        Everything read is validated (the file's checksum-free content is not trusted): a
        missing, corrupt, foreign or malformed file raises :class:`PolicyFileError` with one line.
        """
        path = os.fspath(path)
        if not os.path.exists(path):
            raise PolicyFileError(f"policy file {path} does not exist")
        if not os.path.isfile(path):
            raise PolicyFileError(f"{path} is not a regular file (a directory, FIFO or device)")
        try:
            with zipfile.ZipFile(path) as zf:
                names = zf.namelist()
                if _META_MEMBER not in names:
                    raise PolicyFileError(f"{path} is not an SfM policy file (no {_META_MEMBER}; "
                                          f"a dataset or another model?)")
                meta = json.loads(zf.read(_META_MEMBER))
                if not isinstance(meta, dict) or meta.get("format") != FORMAT:
                    got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
                    raise PolicyFileError(f"{path} is not an SfM policy file (format {got!r})")
                arrays = {n[:-4]: np.load(io.BytesIO(zf.read(n)), allow_pickle=False)
                          for n in names if n.endswith(".npy")}
        except PolicyFileError:
            raise
        except (zipfile.BadZipFile, zlib.error, KeyError, ValueError, OSError, EOFError,
                UnicodeDecodeError, NotImplementedError, RuntimeError, SyntaxError,
                tokenize.TokenError) as e:
            # (zipfile raises RuntimeError for a member flagged as encrypted; numpy parses a
            # .npy header as a Python literal: damaged, it raises SyntaxError or TokenError)
            why = str(e).splitlines()[0] if str(e) else ""
            raise PolicyFileError(f"{path} is not a readable SfM policy file "
                                  f"({type(e).__name__}: {why})") from None
        try:
            return cls._from_file_content(meta, arrays, env, path)
        except PolicyFileError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            if isinstance(e, KeyError):
                why = f"missing {why}"
            raise PolicyFileError(f"{path} is a malformed SfM policy file ({why})") from None

    @classmethod
    def _from_file_content(cls, meta: dict, arrays: dict, env, path: str) -> SfMPolicy:
        version = meta.get("format_version", 0)
        if isinstance(version, bool) or not isinstance(version, int) or version < 1:
            raise PolicyFileError(f"{path} has format version {version!r}; expected an integer")
        if version > FORMAT_VERSION:
            raise PolicyFileError(f"{path} has format version {version}; this package reads up "
                                  f"to {FORMAT_VERSION}")
        if not isinstance(meta.get("feature_spec"), dict):
            raise ValueError("feature_spec must be a JSON object")
        spec = FeatureSpec.from_dict(meta["feature_spec"])
        if version == 1:
            proj_arrays = _version1_projector_arrays(meta, arrays)
        else:
            proj_arrays = {k[len("projector."):]: v for k, v in arrays.items()
                           if k.startswith("projector.")}
        proj = EigenspaceProjector.from_arrays(proj_arrays)
        if proj.n_known_ != spec.n_features:
            raise ValueError(f"the projector has {proj.n_known_} known columns but the feature "
                             f"spec makes {spec.n_features}")
        thresholds = np.asarray(arrays["thresholds"])
        n_act = len(spec.action_nvec)
        signed = proj.n_missing_ == n_act
        want = (n_act, 2) if signed else (0, 2)
        bad = (thresholds.shape != want or thresholds.dtype.kind not in "fiu"
               or not np.all(np.isfinite(thresholds)))
        if bad or (signed and np.any(thresholds[:, 0] > thresholds[:, 1])):
            raise ValueError(f"thresholds must be finite (lo <= hi) of shape {want}, got "
                             f"{thresholds.shape}")
        if not signed and proj.n_missing_ != sum(spec.action_nvec):
            raise ValueError(f"the projector reconstructs {proj.n_missing_} columns; commands "
                             f"{tuple(spec.action_nvec)} need {n_act} or {sum(spec.action_nvec)}")
        training = meta.get("training") or {}
        if not isinstance(training, dict):
            raise ValueError("training must be a JSON object")
        env_id = meta.get("env_id")
        policy = cls(proj, spec, thresholds, env_id if isinstance(env_id, str) else None,
                     training)
        if env is not None:
            policy.check_env(env, path)
        return policy

    def check_env(self, env, path="the policy") -> None:
        """Raise PolicyFileError unless ``env`` has this policy's sensor layout and actions."""
        names = tuple(getattr(env.unwrapped, "sensor_names", ()))
        if names != self.sensor_names:
            raise PolicyFileError(
                f"{path} was fitted on sensors [{', '.join(self.sensor_names)}] but the env has "
                f"[{', '.join(names)}]")
        nvec = tuple(int(n) for n in getattr(env.action_space, "nvec", ()))
        if nvec != tuple(self.feature_spec.action_nvec):
            raise PolicyFileError(f"{path} commands {tuple(self.feature_spec.action_nvec)} but "
                                  f"the env's action space is {env.action_space}")


def _version1_projector_arrays(meta: dict, arrays: dict) -> dict:
    """The projector of a format-1 file (run-time arrays and a few numbers in the metadata; no
    training statistics, so no ``partial_fit``), as :meth:`EigenspaceProjector.from_arrays`
    takes it."""
    out = {k: arrays[k] for k in _V1_ARRAYS}
    params = meta["projector"]
    if not isinstance(params, dict):
        raise ValueError("projector must be a JSON object")
    unknown = sorted(set(params) - set(EigenspaceProjector._param_names()))
    if unknown:
        raise ValueError(f"unknown projector parameter {unknown[0]!r}")
    out.update({f"param.{k}": np.asarray("none" if v is None else v) for k, v in params.items()})
    n_seen = meta["n_samples_seen"]
    for key in ("n_components", "n_known"):
        if isinstance(meta[key], bool) or not isinstance(meta[key], int):
            raise ValueError(f"{key} must be an integer, got {meta[key]!r}")
    out["n_components_"] = np.asarray(meta["n_components"], dtype=np.int64)
    out["n_known_"] = np.asarray(meta["n_known"], dtype=np.int64)
    out["n_missing_"] = np.asarray(np.asarray(arrays["intercept_"]).shape[0], dtype=np.int64)
    out["n_samples_seen_"] = np.asarray(float(n_seen))
    out["n_rows_seen_"] = np.asarray(int(n_seen), dtype=np.int64)
    out["rank_floor_"] = np.asarray(float(meta["rank_floor"]))
    out["noise_variance_"] = np.asarray(float(meta["noise_variance"]))
    s = np.asarray(arrays["singular_values_"], dtype=np.float64)
    out["explained_variance_"] = s**2 / max(float(n_seen), 1.0)
    out["rank_ratios_"] = np.empty(0)
    return out


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def signed_actions(actions, nvec) -> np.ndarray:
    """Action indices -> signed values (index ``a`` of an n-valued command -> ``a - (n-1)/2``)."""
    return np.asarray(actions, dtype=np.float64) - (np.asarray(nvec, dtype=np.float64) - 1) / 2


#: Named configurations: the features and :func:`fit_policy` settings each stands for.
#: ``paper`` is exactly the paper's section 9 (raw sensor channels and commands, standardised,
#: SVD, rank at the largest adjacent singular-value ratio, least-squares projection, fixed +-0.5
#: quantisation); ``default`` is this package's choice (docs/sfm.md says why); ``ols`` is the
#: baseline that explains what the eigenspace adds: ordinary least squares on the default features.
PRESETS = {
    "default": {"features": "default", "solver": "ppca", "thresholds": "learned",
                "min_support": 5},
    "paper": {"features": "raw", "solver": "lstsq", "thresholds": "fixed", "min_support": 0},
    "ols": {"features": "default", "solver": "ols", "thresholds": "learned", "min_support": 5},
}


def preset(name: str, sensor_names) -> tuple[FeatureSpec, dict]:
    """``(feature_spec, fit_policy keyword arguments)`` of preset ``name`` (:data:`PRESETS`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    p = PRESETS[name]
    spec = (default_feature_spec(sensor_names) if p["features"] == "default"
            else FeatureSpec(obs_names=tuple(sensor_names)))
    return spec, {"solver": p["solver"], "thresholds": p["thresholds"],
                  "min_support": p["min_support"]}


#: Most columns a fit accepts: its SVD costs O(columns^3) and its statistics O(columns^2) memory.
MAX_COLUMNS = 10_000


def _memory_bytes() -> int:
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def check_fit_size(n_rows: int, n_columns: int) -> None:
    """ValueError (one line) before allocating, when a fit of ``n_rows`` x ``n_columns`` (features
    plus commands) would not fit in half the machine's memory or exceeds :data:`MAX_COLUMNS`."""
    if n_columns > MAX_COLUMNS:
        raise ValueError(f"{n_columns} feature columns is more than the {MAX_COLUMNS} a fit "
                         "accepts (check --history / --traces)")
    need = 8 * (3 * n_rows * n_columns + 4 * n_columns * n_columns)
    have = _memory_bytes() // 2
    if need > have:
        raise ValueError(f"a fit of {n_rows} rows x {n_columns} columns needs about "
                         f"{need / 2**30:.1f} GiB; at most {have / 2**30:.1f} GiB (half this "
                         "machine's memory) is allowed: use fewer rows or features")


def fit_columns(feature_spec: FeatureSpec, encoding: str = "signed") -> int:
    """Columns of a stacked training row ``[features, commands]``: ``n_features`` plus one signed
    column per command, or one one-hot column per command value."""
    if encoding not in ("signed", "onehot"):
        raise ValueError(f"encoding must be 'signed' or 'onehot', got {encoding!r}")
    n_targets = (sum(feature_spec.action_nvec) if encoding == "onehot"
                 else len(feature_spec.action_nvec))
    return int(feature_spec.n_features) + int(n_targets)


def min_fit_rows(feature_spec: FeatureSpec, encoding: str = "signed") -> int:
    """Fewest training rows (time steps) an SfM fit of ``feature_spec`` accepts: one more than
    the columns of a stacked row ``[features, commands]`` (``n_features`` plus 2 signed command
    columns, or 6 one-hot ones).

    Why: the projector centres the rows before its SVD, and ``n`` centred rows span at most
    ``n - 1`` dimensions, so with ``n <= p`` rows (``p`` columns) the trailing ``p - n + 1``
    singular values are zero by construction, whatever the robot did, and the rank rule (the
    largest adjacent ratio ``s_i / s_(i+1)``, which needs two nonzero values to compare) finds
    its cliff at ``n - 1``: an artefact of the row count (2 rows: rank 1 at a ratio of 1e16).
    With ``p + 1`` rows every singular value can be nonzero, so the spectrum the rule ranks,
    and the map solved from it, are properties of the data (the Gram matrix of the known
    columns, which ``ols`` inverts, can then have full rank too). The code itself runs from 2
    rows (:meth:`EigenspaceProjector.fit`); this is the identifiability floor, not a quality
    bar: a fit at the floor is well posed, not good (measured: 1,200 teacher steps and
    up). Learned thresholds need no more: a command value absent from the training rows is
    never predicted (its threshold is stored at +-1e6), at any size.
    """
    return fit_columns(feature_spec, encoding) + 1


def check_fit_rows(n_rows: int, feature_spec: FeatureSpec, encoding: str = "signed",
                   what: str = "the training data") -> None:
    """ValueError (one line, naming ``what``, its rows and the minimum) when ``n_rows`` is
    below :func:`min_fit_rows`."""
    need = min_fit_rows(feature_spec, encoding)
    if n_rows < need:
        n_cmd = need - 1 - feature_spec.n_features
        raise ValueError(f"{what} {'have' if what.startswith('datasets ') else 'has'} "
                         f"{n_rows} rows; an SfM fit of {feature_spec.n_features} features + "
                         f"{n_cmd} command columns needs at least {need} (one more than the "
                         "columns of a stacked row)")


def fit_policy(data, feature_spec: FeatureSpec | None = None, *, n_components=None,
               solver: str = "ppca", rank_rtol: float = 1e-3, thresholds: str = "learned",
               alpha: float = 1e-3, encoding: str = "signed",
               min_support: int = 5) -> SfMPolicy:
    """Fit an :class:`SfMPolicy` to a recorded :class:`~mkv_env.dataset.Dataset`.

    Args:
        data: the teacher's recording (any number of episodes), or a list of recordings with
            the same sensor layout (e.g. wandering runs plus jam runs), stacked; at least
            :func:`min_fit_rows` steps in all (fewer: ValueError, before any work).
        feature_spec: the features; default
            :func:`~mkv_env.features.default_feature_spec`.
        n_components: kept eigenvectors; ``None`` = the paper's largest-ratio rule.
        solver, rank_rtol, alpha: passed to :class:`EigenspaceProjector`.
        thresholds: ``"learned"`` (balanced accuracy on the training rows) or ``"fixed"``.
        encoding: the command columns of the training matrix: ``"signed"`` (one column per
            command, -1/0/+1, quantised by thresholds) or ``"onehot"`` (one column per command
            value, decoded by the largest reconstructed entry).
        min_support: a sensor channel that leaves its most common value in fewer than this many
            training rows (a bump switch pressed once or twice) is held constant in the fit, it
            and every feature made from it, so the policy ignores it instead of extrapolating a
            response fitted to one or two rows (:func:`rare_channels`; a rear bump seen
            once gave a trace coefficient of -7.4 on the drive command, and the policy reversed
            into walls for good). 0 (the paper) uses every channel; the default and ols presets
            use 5 (chosen on development sets 100-139 against 0 and 20: at 1,200 teacher steps
            escape 0.953 vs 0.910 with 0, paired +0.043 [+0.013, +0.078], failures 0/40 vs
            6/40; 20 also held the front bumpers constant, which small sets press only 10-30
            rows, and escaped 0.853).
    """
    if thresholds not in ("learned", "fixed"):
        raise ValueError(f"thresholds must be 'learned' or 'fixed', got {thresholds!r}")
    if encoding not in ("signed", "onehot"):
        raise ValueError(f"encoding must be 'signed' or 'onehot', got {encoding!r}")
    t0 = time.perf_counter()
    datasets = list(data) if isinstance(data, list | tuple) else [data]
    if not datasets:
        raise ValueError("no dataset to fit")
    names = list(datasets[0].sensor_names)
    for d in datasets[1:]:
        if list(d.sensor_names) != names:
            raise ValueError(f"datasets have different sensor layouts: {names} vs "
                             f"{list(d.sensor_names)}")
    if feature_spec is None:
        feature_spec = default_feature_spec(names, ACTION_NVEC)
    elif tuple(feature_spec.obs_names) != tuple(names):
        raise ValueError("the feature spec's obs_names differ from the dataset's sensor names")
    n_targets = (sum(feature_spec.action_nvec) if encoding == "onehot"
                 else len(feature_spec.action_nvec))
    check_fit_size(sum(d.n_steps for d in datasets), feature_spec.n_features + n_targets)
    check_fit_rows(sum(d.n_steps for d in datasets), feature_spec, encoding)
    builder = FeatureBuilder(feature_spec)
    feats = np.concatenate([builder.transform(d["observations"], d["actions"], episode_starts(d))
                            for d in datasets])
    rare = rare_channels(np.concatenate([np.asarray(d["observations"]) for d in datasets]),
                         names, min_support)
    held = [i for i, f in enumerate(feature_spec.feature_names) if _source_channel(f) in rare]
    feats[:, held] = 0.0
    actions = np.concatenate([np.asarray(d["actions"], dtype=np.int64) for d in datasets])
    if encoding == "onehot":
        target = onehot_actions(actions, feature_spec.action_nvec)
    else:
        target = signed_actions(actions, feature_spec.action_nvec)
    proj = EigenspaceProjector(n_components, rank_rtol=rank_rtol, solver=solver, alpha=alpha)
    proj.fit(feats, target)
    values = feats @ proj.coef_ + proj.intercept_
    if encoding == "onehot":
        thr = np.zeros((0, 2))
    elif thresholds == "learned":
        thr = learn_thresholds(values, actions)
    else:
        thr = np.tile(FIXED_THRESHOLDS, (target.shape[1], 1))
    env_ids = sorted({str(d.metadata.get("env_id")) for d in datasets})
    training = {
        "rows": int(len(actions)),
        "episodes": int(sum(d.n_episodes for d in datasets)),
        "datasets": [{"env_id": d.metadata.get("env_id"), "episodes": int(d.n_episodes),
                      "rows": int(d.n_steps), "sha256": d.metadata.get("content_sha256"),
                      "teacher": d.metadata.get("policy")} for d in datasets],
        "encoding": encoding,
        "thresholds": thresholds if encoding == "signed" else "argmax",
        "min_support": int(min_support),
        "rare_channels": rare,
        "wall_s": round(time.perf_counter() - t0, 4),
    }
    return SfMPolicy(proj, feature_spec, thr, env_ids[0] if len(env_ids) == 1 else None,
                     training)


def rare_channels(observations, names, min_support: int) -> dict:
    """``{channel: rows}`` of the channels whose value differs from its most common value in
    fewer than ``min_support`` rows of ``observations`` (n, n_channels)."""
    if not (isinstance(min_support, int | np.integer) and min_support >= 0):
        raise ValueError(f"min_support must be an integer >= 0, got {min_support!r}")
    obs = np.asarray(observations, dtype=np.float64)
    out = {}
    for j, name in enumerate(names):
        _, counts = np.unique(obs[:, j], return_counts=True)
        active = int(len(obs) - counts.max()) if len(obs) else 0
        if active < min_support:
            out[str(name)] = active
    return out


def _source_channel(feature_name: str) -> str:
    """``"bump_rear~0.8"``, ``"bump_rear[t-1]"`` -> ``"bump_rear"`` (commands: themselves)."""
    return feature_name.split("[", 1)[0].split("~", 1)[0]


def onehot_actions(actions, nvec) -> np.ndarray:
    """Action indices (n, n_act) -> one-hot blocks (n, sum(nvec)), 0/1 floats."""
    actions = np.asarray(actions, dtype=np.int64)
    blocks = [np.eye(int(k))[actions[:, j]] for j, k in enumerate(nvec)]
    return np.concatenate(blocks, axis=1)


def episode_starts(data) -> np.ndarray:
    """Boolean (n_steps,) flags, True at the first step of every episode."""
    starts = np.zeros(data.n_steps, dtype=bool)
    for sl in data.episode_slices():
        starts[sl.start] = True
    return starts


def load_spec(arg: str, env, seed):
    """Policy-spec loader for ``sfm:PATH``."""
    from mkv_env.policies import PolicySpecError

    if not arg:
        raise PolicySpecError("sfm: needs a path, e.g. sfm:policy.npz")
    try:
        return SfMPolicy.load(arg, env)
    except PolicyFileError as e:
        raise PolicySpecError(str(e)) from None
