"""Every option of every command-line command has a help line.

The parsers of every console script in pyproject.toml (``[project.scripts]``) are built and walked
(``parser._actions``, and each subcommand's parser through ``_SubParsersAction.choices``): every
action except the automatic ``-h/--help``, positionals and the subcommand list included, must have
a non-empty help text that is not ``argparse.SUPPRESS``, and each subcommand must have a line in
its parent's ``--help``.
"""

from __future__ import annotations

import argparse
import importlib
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: Console script -> "module:function" building its parser (the module of its ``main``).
PARSERS = {
    "mkv": "sfm_learn.cli:build_parser",
    "calib": "calib.cli:_parser",
}


def _build(script: str) -> argparse.ArgumentParser:
    module, _, func = PARSERS[script].partition(":")
    return getattr(importlib.import_module(module), func)()


def _name(action: argparse.Action) -> str:
    return "/".join(action.option_strings) or action.metavar or action.dest


def _has_help(text) -> bool:
    return isinstance(text, str) and bool(text.strip()) and text != argparse.SUPPRESS


def walk(parser: argparse.ArgumentParser, path: str):
    """(command path, parser) of ``parser`` and every subcommand under it, depth first."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from walk(sub, f"{path} {name}")


def missing_help(parser: argparse.ArgumentParser, path: str) -> list[str]:
    """'command option' of every action without a help text, and every subcommand without a
    line in its parent's --help."""
    bad = []
    for where, p in walk(parser, path):
        for action in p._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            if not _has_help(action.help):
                bad.append(f"{where} {_name(action)}")
            if isinstance(action, argparse._SubParsersAction):
                listed = {a.dest: a.help for a in action._choices_actions}
                bad += [f"{where} {name} (subcommand)" for name in action.choices
                        if not _has_help(listed.get(name))]
    return bad


def test_every_console_script_has_its_parser_listed():
    tomllib = pytest.importorskip("tomllib")
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == set(PARSERS), "add the new console script's parser to PARSERS"
    # each script runs its command through mkv_sfm_launch, which imports the parser's module
    import mkv_sfm_launch

    for script, target in scripts.items():
        assert target == f"mkv_sfm_launch:{script}", script
        launched = getattr(mkv_sfm_launch, script).__doc__
        assert PARSERS[script].partition(":")[0] + ".main" in launched, script


@pytest.mark.parametrize("script", sorted(PARSERS))
def test_every_option_has_help(script):
    parser = _build(script)
    commands = [where for where, _ in walk(parser, script)]
    assert len(commands) > 1, f"{script}: no subcommands found; the walk is broken"
    bad = missing_help(parser, script)
    assert not bad, "options without a help text: " + "; ".join(bad)


@pytest.mark.parametrize("script", sorted(PARSERS))
def test_every_help_page_formats(script):
    # a stray '%' in a help text breaks --help (argparse %-formats it) only when it is shown
    for where, p in walk(_build(script), script):
        assert p.format_help(), where


def test_missing_help_is_reported_by_command_and_option():
    p = argparse.ArgumentParser(prog="x")
    p.add_argument("--ok", help="fine")
    sub = p.add_subparsers(dest="command", help="the command")
    s = sub.add_parser("go", help="go somewhere")
    s.add_argument("where", metavar="WHERE.csv")
    s.add_argument("--quiet", action="store_true", help=argparse.SUPPRESS)
    s.add_argument("--fast", action="store_true", help="  ")
    sub.add_parser("stay")
    assert missing_help(p, "x") == ["x stay (subcommand)", "x go WHERE.csv", "x go --quiet",
                                    "x go --fast"]
