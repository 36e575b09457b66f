"""The ``mkv`` command line (docs/design.md section 6): the command table, the parser and ``main``.

Each command lives in its own module of :mod:`sfm_learn.cli` with ``add_arguments(parser)`` and
``run(args) -> int``; the module is imported only when the parser is built, so it must import
torch/matplotlib/pygame inside functions, never at module level. Adding a command is one
:class:`Command` line in :data:`COMMANDS`.

Bad input ends a command with exit status 2 and one line on stderr, ``mkv <command>: error: ...``:
a :class:`~sfm_learn.cli.common.CliError` from the command, or a ``ValueError``/``TypeError``/
``OSError`` from the library (whose messages are one line). An interrupt (Ctrl-C) exits with 130
and leaves no partial output file. Set ``MKV_DEBUG=1`` to get the traceback instead.

Adding a policy spec prefix (``sfm:``, ``ppo:``, ``bc:``): add a line to
``sfm_learn.POLICY_LOADERS`` naming ``loader(arg, env, seed) -> policy`` as ``"module:function"``.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
import warnings
from dataclasses import dataclass

import sfm_learn  # noqa: F401  (registers the policy specs)
from sfm_common.cli import (
    OneLineParser,
    UsageError,
    caused_by_interrupt,
    interrupts_not_lost,
    one_line,
)
from sfm_learn.cli.common import CliError

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

__all__ = ["COMMANDS", "Command", "build_parser", "main"]


@dataclass(frozen=True)
class Command:
    """One subcommand: its name, one-line help, and the module holding ``add_arguments`` and
    ``run`` (imported when the parser is built)."""

    name: str
    help: str
    module: str


COMMANDS: list[Command] = [
    Command("record", "record a policy's episodes into a dataset file", "sfm_learn.cli.record"),
    Command("eval", "evaluate policies on the same seeded episodes", "sfm_learn.cli.eval"),
    Command("play", "render an episode of a policy (window, or frames headless)",
            "sfm_learn.cli.play"),
    Command("teleop", "drive the robot with the arrow keys and record the run",
            "sfm_learn.cli.teleop"),
    Command("fit", "fit a shape-from-motion (eigenspace) policy to a dataset",
            "sfm_learn.cli.fit"),
    Command("compare", "teacher vs SfM commands on held-out runs (the paper's Figure 3)",
            "sfm_learn.cli.compare"),
    Command("train-ppo", "train an SB3 PPO policy on the env reward", "sfm_learn.cli.train_ppo"),
    Command("train-bc", "behaviour-clone an SB3 policy from a dataset", "sfm_learn.cli.train_bc"),
    Command("train-dagger", "DAgger: the teacher labels the learner's own runs",
            "sfm_learn.cli.train_dagger"),
    Command("sweep", "run a sweep spec (learners x seeds x budgets) or summarise one",
            "sfm_learn.cli.sweep"),
    Command("demo", "the main job end to end on defaults; writes DIR/report.md",
            "sfm_learn.cli.demo"),
    Command("export", "write a dataset file into Minari (offline-RL dataset standard)",
            "sfm_learn.cli.export"),
    Command("import-minari", "read a Minari dataset written by mkv export into a dataset file",
            "sfm_learn.cli.import_minari"),
]


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="mkv", description="MK-V teleop data, shape-from-motion policies, "
                                              "baselines and evaluation.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser,
                           metavar="COMMAND",
                           help="the command to run (mkv COMMAND --help lists its options)")
    for cmd in COMMANDS:
        module = importlib.import_module(cmd.module)
        sp = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        module.add_arguments(sp)
        sp.set_defaults(_run=module.run, _prog=f"mkv {cmd.name}")
    return p


@contextlib.contextmanager
def _held_warnings():
    """Library warnings (Gymnasium's "MKV-v0 is out of date", torch's on a pickled file) are
    held while a command runs: shown at its end when it succeeds, dropped when it fails, so that
    a failing command's one-line error is the only line it prints."""
    with warnings.catch_warnings(record=True) as held:
        yield
    for w in held:  # reached only on success: an exception skips this
        warnings.showwarning(w.message, w.category, w.filename, w.lineno, w.file, w.line)


def main(argv=None, *, nested: bool = False) -> int:
    """Entry point of the ``mkv`` console script; returns the exit status. ``nested``: called as
    a stage of another command (``mkv demo``), a Ctrl-C propagates as ``KeyboardInterrupt``
    instead of being reported here (the outer command reports it, once)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = "mkv"
    debug = bool(os.environ.get("MKV_DEBUG"))
    try:
        args = build_parser().parse_args(argv)
        prog = args._prog
        with _held_warnings(), interrupts_not_lost():
            try:
                return int(args._run(args) or 0)
            except Exception as e:  # a Ctrl-C that Python wrapped (a hook, an extension's
                if caused_by_interrupt(e):  # import): still a Ctrl-C
                    raise KeyboardInterrupt from e
                raise
    except KeyboardInterrupt:
        if nested:
            raise
        print(f"{prog}: interrupted; no output written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except UsageError as e:
        print(f"{e.prog}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except (CliError, ValueError, TypeError) as e:
        if debug:
            raise
        print(f"{prog}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as e:
        if debug:
            raise
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"{prog}: error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
