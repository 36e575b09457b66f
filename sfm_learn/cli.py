"""The ``mkv`` command line (DESIGN.md section 6).

::

    mkv record --env MKV-v0 --policy teacher --episodes N --seed S --out DATA.npz
    mkv eval   --env MKVJam-v0 --policy SPEC --episodes N --seed S [--json OUT.json]
    mkv play   --policy SPEC [--env ID] [--seed S] [--out FRAMES_DIR | OUT.gif]

Bad input (unknown env id, bad policy spec, missing or corrupt file, bad numbers) ends the
command with exit status 2 and one line on stderr, ``mkv <command>: error: ...``; an interrupt
(Ctrl-C) exits with 130 and leaves no partial output file.

Adding a command (fit, compare, train-ppo, train-bc, demo, bench, ...): write, in your own module,
``add_arguments(parser)`` and ``run(args) -> int`` (raise :class:`CliError` for user mistakes; long
work may use :func:`progress_for`), then add one :class:`Command` line to :data:`COMMANDS` with
``"module:function"`` strings. The module is imported only when the parser is built, so it must
import torch/matplotlib/pygame inside functions, never at module level.

Adding a policy spec prefix (``sfm:``, ``ppo:``, ``bc:``): add a line to
``sfm_learn.POLICY_LOADERS``
naming ``loader(arg, env, seed) -> policy`` as ``"module:function"``; it is imported only when a
spec with that prefix is used.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass

from mkv_env.dataset import DatasetError
from mkv_env.files import atomic_path
from mkv_env.policies import PolicySpecError, make_policy, register_policy_loader
from mkv_env.script import ScriptError
from sfm_learn import POLICY_LOADERS

DEFAULT_ENV = "MKV-v0"
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class CliError(Exception):
    """A user mistake: printed as one line, exit status 2."""


@dataclass(frozen=True)
class Command:
    """One subcommand: its name, one-line help, and where its argument set-up and runner live
    (callables, or ``"module:function"`` strings imported when the parser is built)."""

    name: str
    help: str
    add_arguments: Callable | str
    run: Callable | str


def _register_policy_loaders() -> None:
    for prefix, target in POLICY_LOADERS.items():
        register_policy_loader(prefix, target, replace=True)


# ---------------------------------------------------------------------- argument types
# argparse ``type=`` functions shared by every command: a bad value is one line,
# "argument --x: expected a positive integer, got '-3'".
def _number(text: str, cast, ok, expected: str):
    try:
        v = cast(text)
    except ValueError:
        v = None
    if v is None or not ok(v):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return v


def _positive_int(text: str) -> int:
    return _number(text, int, lambda v: v >= 1, "a positive integer")


def _non_negative_int(text: str) -> int:
    return _number(text, int, lambda v: v >= 0, "an integer >= 0")


def _seed(text: str) -> int:
    return _number(text, int, lambda v: 0 <= v < 2**62, "a non-negative integer")


def _positive_float(text: str) -> float:
    return _number(text, float, lambda v: math.isfinite(v) and v > 0, "a positive number")


def _non_negative_float(text: str) -> float:
    return _number(text, float, lambda v: math.isfinite(v) and v >= 0, "a number >= 0")


def _fraction(text: str) -> float:
    return _number(text, float, lambda v: 0.0 <= v < 1.0, "a fraction in [0, 1)")


def _env_kwargs(text: str) -> dict:
    try:
        v = json.loads(text)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"not valid JSON ({e.msg})") from None
    if not isinstance(v, dict):
        raise argparse.ArgumentTypeError("expected a JSON object, e.g. '{\"n_clutter\": 5}'")
    return v


def _add_env_args(p: argparse.ArgumentParser, required: bool = False) -> None:
    p.add_argument("--env", default=None if required else DEFAULT_ENV, required=required,
                   metavar="ID", help="registered env id (MKV-v0, MKVJam-v0)"
                   + ("" if required else f"; default {DEFAULT_ENV}"))
    p.add_argument("--env-kwargs", type=_env_kwargs, default={}, metavar="JSON",
                   help="extra gymnasium.make arguments as a JSON object")


def _add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bar")


# ---------------------------------------------------------------------- shared helpers
def check_env_and_policy(env_id: str, env_kwargs: dict, spec: str | None) -> None:
    """Fail fast (CliError) on an unknown env id, bad env kwargs or a bad policy spec."""
    from mkv_env.recorder import make_env

    try:
        env = make_env(env_id, env_kwargs)
    except ValueError as e:
        raise CliError(str(e).splitlines()[0]) from None
    try:
        if spec is not None:
            make_policy(spec, env, seed=0)
    finally:
        env.close()


def check_output_path(path: str, what: str = "output") -> None:
    """The directory of ``path`` must exist and ``path`` must not be a directory."""
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise CliError(f"{what} directory {directory} does not exist")
    if os.path.isdir(path):
        raise CliError(f"{what} {path} is a directory")


def progress_for(args, total: int, desc: str):
    from mkv_env.progress import Progress

    return Progress(total, desc, enabled=False if getattr(args, "quiet", False) else None,
                    unit="ep")


# ---------------------------------------------------------------------- record
def add_record_arguments(p: argparse.ArgumentParser) -> None:
    _add_env_args(p, required=True)
    p.add_argument("--policy", required=True, metavar="SPEC",
                   help="teacher, teacher:key=value,..., random, script:PATH, ...")
    p.add_argument("--episodes", type=_positive_int, required=True, metavar="N")
    p.add_argument("--seed", type=_seed, default=0, metavar="S",
                   help="episode i uses env seed S+i (default 0)")
    p.add_argument("--out", required=True, metavar="DATA.npz")
    _add_quiet(p)


def run_record(args) -> int:
    from mkv_env.dataset import save
    from mkv_env.recorder import record, summarize

    check_output_path(args.out)
    check_env_and_policy(args.env, args.env_kwargs, args.policy)
    with progress_for(args, args.episodes, f"record {args.env}") as bar:
        data = record(args.env, args.policy, args.episodes, args.seed, args.env_kwargs,
                      on_episode=lambda i, n: bar.update(1))
    save(data, args.out)
    s = summarize(data)
    line = (f"{s['episodes']} episodes, {s['steps']} steps, {s['jams']} jams, "
            f"{s['escapes']} escapes, stuck fraction {s['stuck_fraction']:.3f}")
    if "escaped_episodes" in s:
        line += f", {s['escaped_episodes']}/{s['episodes']} episodes escaped"
    print(line)
    print(f"wrote {args.out}")
    return 0


# ---------------------------------------------------------------------- play
def add_play_arguments(p: argparse.ArgumentParser) -> None:
    _add_env_args(p)
    p.add_argument("--policy", required=True, metavar="SPEC")
    p.add_argument("--seed", type=_seed, default=0, metavar="S")
    p.add_argument("--max-steps", type=_positive_int, default=None, metavar="N",
                   help="stop after N steps (default: the episode's own end)")
    p.add_argument("--out", metavar="DIR|OUT.gif",
                   help="write frames (PNG files in DIR, or one animated GIF) instead of a "
                        "window; the default without a display is play_frames/")


def has_display() -> bool:
    """Whether a pygame window can be opened (not SDL's dummy driver, an X/Wayland display)."""
    if os.environ.get("SDL_VIDEODRIVER", "") in ("dummy", "offscreen"):
        return False
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def run_play(args) -> int:
    from mkv_env.recorder import make_env, policy_seed

    out = args.out
    if out is None and not has_display():
        out = "play_frames"
    gif = out is not None and out.lower().endswith(".gif")
    if out is not None:
        if gif:
            check_output_path(out)
        elif os.path.exists(out) and not os.path.isdir(out):
            raise CliError(f"frames directory {out} exists and is not a directory")
    if gif:
        try:
            import PIL.Image  # noqa: F401  (only to write GIFs)
        except ImportError:
            raise CliError("writing a GIF needs Pillow; give a directory for PNG frames") from None
    check_env_and_policy(args.env, args.env_kwargs, args.policy)
    try:
        import pygame  # noqa: F401
    except ImportError:
        raise CliError("mkv play needs pygame (pip install 'mkv-sfm[render]')") from None

    env = make_env(args.env, args.env_kwargs, render_mode="rgb_array" if out else "human")
    frames = []
    try:
        policy = make_policy(args.policy, env, seed=policy_seed(args.seed))
        if hasattr(policy, "reset"):
            policy.reset(seed=policy_seed(args.seed))
        obs, info = env.reset(seed=args.seed)
        if out:
            frames.append(env.render())
        steps, ret, start = 0, 0.0, True
        while True:
            action, _ = policy.predict(obs, episode_start=start)
            start = False
            obs, reward, terminated, truncated, info = env.step(action)
            ret += float(reward)
            steps += 1
            if out:
                frames.append(env.render())
            if terminated or truncated or (args.max_steps and steps >= args.max_steps):
                break
    finally:
        env.close()
    summary = f"{steps} steps, return {ret:.2f}, distance {info['distance_m']:.2f} m"
    if "escaped" in info:
        summary += ", escaped" if info["escaped"] else ", not escaped"
    print(summary)
    if out:
        written = _write_gif(frames, out, env.metadata.get("render_fps", 10)) if gif \
            else _write_pngs(frames, out)
        print(f"wrote {written}")
    return 0


def _write_pngs(frames, directory: str) -> str:
    import numpy as np
    import pygame

    os.makedirs(directory, exist_ok=True)
    width = max(4, len(str(len(frames))))
    for i, frame in enumerate(frames):
        surface = pygame.surfarray.make_surface(np.ascontiguousarray(frame.transpose(1, 0, 2)))
        pygame.image.save(surface, os.path.join(directory, f"frame_{i:0{width}d}.png"))
    return f"{len(frames)} PNG frames to {directory}"


def _write_gif(frames, path: str, fps: int) -> str:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    with atomic_path(path, ".gif") as tmp:
        images[0].save(tmp, save_all=True, append_images=images[1:],
                       duration=max(1, round(1000 / fps)), loop=0)
    return f"{len(frames)} frames to {path}"


# ---------------------------------------------------------------------- command table
COMMANDS: list[Command] = [
    Command("record", "record a policy's episodes into a dataset file",
            add_record_arguments, run_record),
    Command("eval", "evaluate policies on the same seeded episodes",
            "sfm_learn.eval_cli:add_arguments", "sfm_learn.eval_cli:run"),
    Command("play", "render an episode of a policy (window, or frames headless)",
            add_play_arguments, run_play),
    Command("fit", "fit a shape-from-motion (eigenspace) policy to a dataset",
            "sfm_learn.sfm_cli:add_fit_arguments", "sfm_learn.sfm_cli:run_fit"),
    Command("compare", "teacher vs SfM commands on held-out runs (the paper's Figure 3)",
            "sfm_learn.sfm_cli:add_compare_arguments", "sfm_learn.sfm_cli:run_compare"),
    Command("train-ppo", "train an SB3 PPO policy on the env reward",
            "sfm_learn.ppo:add_arguments", "sfm_learn.ppo:run"),
    Command("train-bc", "behaviour-clone an SB3 policy from a dataset",
            "sfm_learn.bc:add_arguments", "sfm_learn.bc:run"),
    Command("demo", "the main job end to end on defaults; writes DIR/report.md",
            "sfm_learn.demo:add_arguments", "sfm_learn.demo:run"),
]


def _resolve(target):
    if callable(target):
        return target
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


class _UsageError(CliError):
    def __init__(self, prog: str, message: str):
        super().__init__(message)
        self.prog = prog


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of usage + message
        raise _UsageError(self.prog, f"{message} (see {self.prog} --help)")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="mkv", description="MK-V teleop data, shape-from-motion policies, "
                                        "baselines and evaluation.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser,
                           metavar="COMMAND")
    for cmd in COMMANDS:
        sp = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        _resolve(cmd.add_arguments)(sp)
        sp.set_defaults(_run=cmd.run, _prog=f"mkv {cmd.name}")
    return p


def main(argv=None) -> int:
    """Entry point of the ``mkv`` console script; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = "mkv"
    try:
        _register_policy_loaders()
        args = build_parser().parse_args(argv)
        prog = args._prog
        return int(_resolve(args._run)(args) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; no output written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (CliError, DatasetError, PolicySpecError, ScriptError) as e:
        prog = getattr(e, "prog", prog)
        print(f"{prog}: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as e:
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"{prog}: error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_USAGE


def _one_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

__all__ = ["COMMANDS", "CliError", "Command", "POLICY_LOADERS", "build_parser", "main"]
