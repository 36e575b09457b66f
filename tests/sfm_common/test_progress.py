"""Progress bars: drawn on a terminal only, lines printed either way."""

import io

import pytest

from sfm_common.progress import NullBar, progress


class Tty(io.StringIO):
    def isatty(self):
        return True


def test_bar_draws_to_a_terminal():
    pytest.importorskip("tqdm")
    out = Tty()
    with progress(3, "rec", unit="ep", stream=out) as bar:
        for _ in range(3):
            bar.update(1)
    text = out.getvalue()
    assert "rec" in text and "3/3" in text and "ep" in text


def test_no_bar_when_not_a_terminal_or_disabled(capsys):
    quiet = io.StringIO()
    with progress(3, "rec", stream=quiet) as bar:
        bar.update(3)
        bar.write("a line")
    assert quiet.getvalue() == ""
    assert isinstance(bar, NullBar) and bar.n == 3
    assert capsys.readouterr().out == "a line\n"
    with progress(3, "rec", stream=Tty(), enabled=False) as bar:
        assert isinstance(bar, NullBar)


def test_write_goes_above_a_live_bar(capsys):
    pytest.importorskip("tqdm")
    out = Tty()
    with progress(2, "rec", stream=out) as bar:
        bar.write("epoch 1")
        bar.update(2)
    assert "epoch 1" in capsys.readouterr().out
