"""What every ``mkv`` command shares: :class:`CliError`, the env arguments, output-path checks,
progress bars. The only module of sfm_learn besides the command modules that knows argparse.
"""

from __future__ import annotations

import argparse
import json
import os

from sfm_common.cli import (  # noqa: F401  (re-exported for the command modules)
    fraction,
    int_in_range,
    non_negative_float,
    non_negative_int,
    one_line,
    positive_float,
    positive_int,
    seed,
)
from sfm_common.progress import progress

DEFAULT_ENV = "MKV-v0"

#: Stated maxima (a typo of extra zeros is an error, not a week of computing).
MAX_EPISODES = 10_000_000
MAX_TIMESTEPS = 10_000_000_000
MAX_ENVS = 256
episodes_type = int_in_range(1, MAX_EPISODES)
timesteps_type = int_in_range(1, MAX_TIMESTEPS)
n_envs_type = int_in_range(1, MAX_ENVS)


class CliError(Exception):
    """A user mistake: printed as one line, exit status 2."""


def env_kwargs_type(text: str) -> dict:
    """argparse type of ``--env-kwargs``: a JSON object."""
    try:
        v = json.loads(text)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"not valid JSON ({e.msg})") from None
    if not isinstance(v, dict):
        raise argparse.ArgumentTypeError("expected a JSON object, e.g. '{\"n_clutter\": 5}'")
    return v


def add_env_arguments(p: argparse.ArgumentParser, required: bool = False) -> None:
    """``--env ID`` and ``--env-kwargs JSON``."""
    p.add_argument("--env", default=None if required else DEFAULT_ENV, required=required,
                   metavar="ID", help="registered env id (MKV-v1, MKVJam-v1, MKV-v0, MKVJam-v0)"
                   + ("" if required else f"; default {DEFAULT_ENV}"))
    p.add_argument("--env-kwargs", type=env_kwargs_type, default={}, metavar="JSON",
                   help="extra gymnasium.make arguments as a JSON object")


def add_quiet_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bar")


#: Help text of the policy specs every --policy accepts.
POLICY_HELP = ("teacher, teacher:key=value,..., random, const:NAME, script:PATH, sfm:PATH, "
               "ppo:PATH, bc:PATH, dagger:PATH, sb3:ALGO:PATH (any Stable-Baselines3 / rl-zoo3 "
               "zip, read without unpickling anything; --trust-pickle for zips that need it)")

#: What --trust-pickle prints when used.
TRUST_WARNING = ("warning: --trust-pickle: sb3: zips and vecnormalize.pkl files are unpickled, "
                 "which can run any code they carry; use it only on files you trust as you "
                 "would a Python script")


def add_trust_argument(p: argparse.ArgumentParser) -> None:
    """``--trust-pickle``: let ``sb3:`` specs unpickle (documented in docs/trust.md)."""
    p.add_argument("--trust-pickle", action="store_true",
                   help="let sb3: specs unpickle the zip's serialized settings and a "
                        "vecnormalize.pkl (runs code from the files: only for files you trust)")


def apply_trust(args) -> None:
    """Honour ``--trust-pickle`` (for this process and its workers), with a warning."""
    import sys

    from sfm_learn.baselines.sb3_models import TRUST_ENV

    if getattr(args, "trust_pickle", False):
        os.environ[TRUST_ENV] = "1"
    if os.environ.get(TRUST_ENV, "") == "1":
        print(TRUST_WARNING, file=sys.stderr)


def check_spec_files(specs) -> None:
    """Every spec's syntax and file (exists, is a regular file), and for ``sb3:`` its algorithm,
    before any file is read (CliError naming the bad spec)."""
    from mkv_env.policies import PolicySpecError, known_prefixes, make_policy

    for spec in specs:
        prefix, _, arg = spec.strip().partition(":")
        try:
            if prefix not in known_prefixes():  # make_policy's own message
                raise PolicySpecError(
                    f"unknown policy spec {spec!r}; known: "
                    + ", ".join(p + {"teacher": "", "random": "", "const": ":NAME"}.get(p, ":PATH")
                                for p in known_prefixes()))
            if prefix == "sb3":
                from sfm_learn.baselines.sb3_models import check_spec

                check_spec(arg)
                continue
        except PolicySpecError as e:
            text = one_line(e)
            raise CliError(text if spec in text else f"--policy {spec}: {text}") from None
        path = spec_path(spec)
        if path is None or prefix == "teacher" or os.path.isfile(path):
            continue
        if not os.path.exists(path) or os.path.isdir(path):
            try:  # the loader's own message (it refuses before reading anything)
                make_policy(spec, None, seed=0)
            except PolicySpecError as e:
                text = one_line(e)
                raise CliError(text if spec in text else f"--policy {spec}: {text}") from None
            raise CliError(f"--policy {spec}: {path}: no such file")
        raise CliError(f"--policy {spec}: {path} is not a regular file")


def check_env_and_policies(env_id: str, env_kwargs: dict, specs=()) -> None:
    """Fail fast (CliError) on an unknown env id, bad env kwargs or a bad policy spec; with
    several specs, the bad one is named. Every spec's file is checked before any is read."""
    from mkv_env.policies import PolicySpecError, make_policy
    from mkv_env.recorder import make_env

    check_spec_files(specs)
    try:
        env = make_env(env_id, env_kwargs)
    except ValueError as e:
        raise CliError(one_line(e)) from None
    try:
        for spec in specs:
            try:
                make_policy(spec, env, seed=0)
            except PolicySpecError as e:
                text = one_line(e)
                if len(specs) > 1 and spec not in text:
                    text = f"--policy {spec}: {text}"
                raise CliError(text) from None
    finally:
        env.close()


def check_output_path(path: str, what: str = "output") -> None:
    """The directory of ``path`` must exist and ``path`` must not be a directory."""
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise CliError(f"{what} directory {directory} does not exist")
    if os.path.isdir(path):
        raise CliError(f"{what} {path} is a directory")


def check_writable(path: str, what: str) -> None:
    directory = os.path.dirname(os.path.abspath(path))
    if not os.access(directory, os.W_OK | os.X_OK):
        raise CliError(f"{what} directory {directory} is not writable")


def progress_for(args, total: int, desc: str, unit: str = "ep"):
    """A progress bar unless ``--quiet`` (drawn only on a terminal)."""
    return progress(total, desc, unit=unit, enabled=False if getattr(args, "quiet", False)
                    else None)


def load_dataset(path: str):
    """A dataset file (mkv_env.dataset.load), with a one-line error when it is missing."""
    from mkv_env.dataset import load

    if not os.path.exists(path):
        raise CliError(f"dataset {path} does not exist")
    if os.path.isdir(path):
        raise CliError(f"{path} is a directory, not a dataset file")
    return load(path)


def check_png_path(path: str, what: str) -> None:
    """An output PNG: its directory exists and the name ends in .png."""
    check_output_path(path, what)
    if not path.lower().endswith(".png"):
        raise CliError(f"{what} {path} must end in .png")


def spec_path(spec: str) -> str | None:
    """The file a policy spec reads (``sfm:P``, ``bc:P``, ``ppo:P``, ``script:P``, ``sb3:ALGO:P``),
    or None (``teacher``, ``random``, ``const:NAME``)."""
    prefix, _, arg = spec.strip().partition(":")
    if prefix == "sb3":
        arg = arg.partition(":")[2]
    return arg.strip() or None if prefix not in ("teacher", "random", "const") else None


def check_outputs(inputs=(), outputs=()) -> None:
    """Every output path must differ from every input and from the other outputs, and must not
    be an existing non-regular file (CliError, one line)."""
    from sfm_common.files import check_distinct, check_writable_target

    try:
        check_distinct(inputs, outputs)
        for out in outputs:
            if out is not None:
                check_writable_target(out)
    except ValueError as e:
        raise CliError(one_line(e)) from None
