"""The ``mkv`` command line: one module per command (see :mod:`sfm_learn.cli.app`)."""

from sfm_learn.cli.app import COMMANDS, build_parser, main
from sfm_learn.cli.common import CliError

__all__ = ["COMMANDS", "CliError", "build_parser", "main"]
