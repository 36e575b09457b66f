"""Atomic writes: the target appears whole or not at all."""

import os
import stat

import pytest

from sfm_common.files import atomic_path, atomic_write_bytes, atomic_write_text


def test_write_replaces_the_target_with_usual_permissions(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    atomic_write_text(target, "new")
    assert target.read_text() == "new"
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~mask
    assert os.listdir(tmp_path) == ["a.txt"]


def test_an_error_while_writing_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "a.bin"
    atomic_write_bytes(target, b"old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        assert tmp.endswith(".bin") and os.path.dirname(tmp) == str(tmp_path)
        with open(tmp, "wb") as f:
            f.write(b"half")
        raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["a.bin"]


def test_suffix_can_be_chosen_for_writers_that_read_it(tmp_path):
    with atomic_path(tmp_path / "plot", ".png") as tmp:
        assert tmp.endswith(".png")
        open(tmp, "w").close()
    assert (tmp_path / "plot").exists()


def test_a_symlink_is_written_through(tmp_path):
    target = tmp_path / "real.txt"
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    atomic_write_text(link, "new")
    assert link.is_symlink() and target.read_text() == "new"


def test_the_replaced_file_keeps_its_permissions(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    os.chmod(target, 0o640)
    atomic_write_text(target, "new")
    assert stat.S_IMODE(target.stat().st_mode) == 0o640


@pytest.mark.parametrize("kind", ["directory", "fifo", "device"])
def test_non_regular_targets_are_refused_and_left_alone(tmp_path, kind):
    if kind == "directory":
        target = tmp_path / "d"
        target.mkdir()
    elif kind == "fifo":
        target = tmp_path / "f"
        os.mkfifo(target)
    else:
        target = "/dev/null"
    with pytest.raises(ValueError, match="directory|not a regular file"):
        atomic_write_text(target, "x")
    if kind == "device":
        assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")] == []


def test_outputs_must_differ_from_inputs_and_each_other(tmp_path):
    from sfm_common.files import check_distinct

    a, b = tmp_path / "a.npz", tmp_path / "b.json"
    a.write_text("x")
    check_distinct([a], [b, tmp_path / "c.png"])
    with pytest.raises(ValueError, match="also an input"):
        check_distinct([a], [tmp_path / "." / "a.npz"])
    link = tmp_path / "l.npz"
    link.symlink_to(a)
    with pytest.raises(ValueError, match="also an input"):
        check_distinct([a], [link])
    with pytest.raises(ValueError, match="two outputs"):
        check_distinct([], [b, tmp_path / "b.json"])


def test_a_failed_write_names_the_users_path_not_the_temporary_one(tmp_path, monkeypatch):
    """A read-only or full file system fails inside mkstemp or the write of the temporary file:
    the error names the path the user gave (".../ro/.tmp-a5lp8rjb.zip" was printed)."""
    import errno
    import tempfile

    from sfm_common.files import atomic_path, atomic_write_text

    def refuse(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(tmp_path / ".tmp-x.zip"))

    target = str(tmp_path / "out.zip")
    with monkeypatch.context() as m:
        m.setattr(tempfile, "mkstemp", refuse)
        with pytest.raises(OSError) as e:
            atomic_write_text(target, "x")
    assert e.value.filename == target and e.value.errno == errno.EROFS
    with pytest.raises(OSError) as e, atomic_path(target) as tmp:
        raise OSError(errno.ENOSPC, "No space left on device", tmp)
    assert e.value.filename == target and e.value.errno == errno.ENOSPC
    assert [p.name for p in tmp_path.iterdir()] == []  # nothing left behind
