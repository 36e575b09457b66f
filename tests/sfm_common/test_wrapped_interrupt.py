"""A Ctrl-C that Python wraps in another exception is still a Ctrl-C: one line, exit 130.

Python wraps a ``KeyboardInterrupt`` raised in a descriptor's ``__set_name__`` (while a class is
created) in a ``RuntimeError``. A Ctrl-C during torch's lazy import of ``torch._dynamo`` (inside
PPO's optimiser set-up) ended ``mkv train-ppo`` that way with a traceback and exit 1 (found by
tests/sfm_learn/cli/test_interrupts.py)."""

import argparse

import pytest

import calib.cli
import sfm_learn.cli.app as app
from sfm_common.cli import caused_by_interrupt


def _wrapped_interrupt() -> RuntimeError:
    class Hook:
        def __set_name__(self, owner, name):
            raise KeyboardInterrupt

    try:
        type("Created", (), {"hook": Hook()})
    except RuntimeError as e:
        return e
    pytest.skip("this Python does not wrap errors of __set_name__")


def test_a_wrapped_interrupt_is_recognised_and_others_are_not():
    assert caused_by_interrupt(_wrapped_interrupt())
    assert caused_by_interrupt(KeyboardInterrupt())
    assert not caused_by_interrupt(RuntimeError("boom"))
    try:
        try:
            raise ValueError("inner")
        except ValueError as inner:
            raise RuntimeError("outer") from inner
    except RuntimeError as e:
        assert not caused_by_interrupt(e)


def _mkv_raises(monkeypatch, err, prog):
    """``mkv`` whose command (named ``prog``) raises ``err``; returns that command's function."""
    def run(args):
        raise err

    class Parser:
        def parse_args(self, argv):
            return argparse.Namespace(_prog=prog, _run=run)

    monkeypatch.setattr(app, "build_parser", Parser)
    return run


def test_mkv_reports_a_wrapped_interrupt_in_one_line(monkeypatch, capsys):
    _mkv_raises(monkeypatch, _wrapped_interrupt(), "mkv train-ppo")
    assert app.main([]) == app.EXIT_INTERRUPTED
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["mkv train-ppo: interrupted; no output written"]


def test_calib_reports_a_wrapped_interrupt_in_one_line(monkeypatch, capsys):
    err = _wrapped_interrupt()

    def plan(args):
        raise err

    monkeypatch.setattr(calib.cli, "_plan", plan)
    assert calib.cli.main(["plan", "poses.csv"]) == 130
    assert capsys.readouterr().err.strip().splitlines() == ["calib: interrupted"]


@pytest.mark.parametrize("err", [RuntimeError("a bug"), ImportError("no module named x")])
def test_other_errors_still_propagate(monkeypatch, err):
    """Errors no Ctrl-C caused (a RuntimeError, an ImportError) are not taken for one."""
    def plan(args):
        raise err

    monkeypatch.setattr(calib.cli, "_plan", plan)
    with pytest.raises(type(err), match=str(err)):
        calib.cli.main(["plan", "poses.csv"])


def _import_interrupted() -> ImportError:
    """What a Ctrl-C inside a pybind11 extension's initialisation raises (scipy.spatial's
    ``_distance_pybind`` during ``mkv demo``'s lazy ``import scipy.stats``)."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise ImportError("initialization failed") from ki
    except ImportError as e:
        return e


def test_an_interrupted_extension_import_is_one_line_in_both_commands(monkeypatch, capsys):
    run = _mkv_raises(monkeypatch, _import_interrupted(), "mkv fit")
    assert app.main([]) == app.EXIT_INTERRUPTED
    with pytest.raises(KeyboardInterrupt):  # a stage of mkv demo: the outer command reports it
        app.main([], nested=True)
    monkeypatch.setattr(calib.cli, "_plan", run)
    assert calib.cli.main(["plan", "poses.csv"]) == 130
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert err_lines == ["mkv fit: interrupted; no output written", "calib: interrupted"]


def test_the_launcher_reports_an_interrupted_extension_import(monkeypatch, capsys):
    import mkv_sfm_launch

    def imp(name):
        raise _import_interrupted()

    monkeypatch.setattr(mkv_sfm_launch.importlib, "import_module", imp)
    assert mkv_sfm_launch.mkv() == mkv_sfm_launch.EXIT_INTERRUPTED
    assert capsys.readouterr().err.strip() == "mkv: interrupted; no output written"

    def broken(name):
        raise ImportError("a real missing module")

    monkeypatch.setattr(mkv_sfm_launch.importlib, "import_module", broken)
    with pytest.raises(ImportError, match="a real missing module"):
        mkv_sfm_launch.calib()
