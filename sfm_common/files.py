"""Atomic file writes, shared by every command that writes a file (datasets, policies, plots,
JSON): write a temporary file in the target's directory, give it the usual permissions, then
rename it onto the target. An error or an interrupt (Ctrl-C) leaves no partial file behind.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "check_distinct",
           "check_writable_target", "same_file"]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_writable_target(path) -> None:
    """ValueError (one line) if ``path`` exists and is not a regular file (after symlinks)."""
    path = os.path.realpath(os.fspath(path))
    if os.path.isdir(path):
        raise ValueError(f"{path} is a directory, not a file to write")
    if os.path.exists(path) and not os.path.isfile(path):
        raise ValueError(f"{path} exists and is not a regular file (a device, FIFO or socket); "
                         "refusing to replace it")


def same_file(a, b) -> bool:
    """Whether paths ``a`` and ``b`` name the same file (symlinks and ``..`` resolved; for
    existing files also hard links)."""
    a, b = os.fspath(a), os.fspath(b)
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_distinct(inputs=(), outputs=()) -> None:
    """ValueError (one line) if an output path is one of the inputs or another output: writing
    it would destroy the input, or lose one of the outputs."""
    inputs = [os.fspath(p) for p in inputs if p is not None]
    outputs = [os.fspath(p) for p in outputs if p is not None]
    for i, out in enumerate(outputs):
        for inp in inputs:
            if same_file(out, inp):
                raise ValueError(f"output {out} is also an input ({inp}); write it elsewhere")
        for other in outputs[:i]:
            if same_file(out, other):
                raise ValueError(f"{out} is given for two outputs; name them differently")


@contextmanager
def atomic_path(path, suffix: str | None = None) -> Iterator[str]:
    """Yield a temporary path beside ``path``; write it inside the ``with`` block.

    On a normal exit the file replaces ``path`` with the permissions of the file it replaces, or
    ``0666 & ~umask`` for a new file (``mkstemp`` makes 0600); on any exception it is removed and
    the exception propagates. A symlink is written through (its target is replaced, the link
    stays). An existing target that is not a regular file (a directory, device, FIFO or socket)
    is refused with ``ValueError`` before anything is written: replacing ``/dev/null`` by a
    regular file is never what was meant. ``suffix`` (default: ``path``'s extension) lets writers
    that pick a format from the name (matplotlib, Pillow) see the right one.
    """
    given = os.fspath(path)
    path = os.path.realpath(given)
    check_writable_target(path)
    if suffix is None:
        suffix = os.path.splitext(path)[1]
    mode = (stat.S_IMODE(os.stat(path).st_mode) if os.path.isfile(path)
            else 0o666 & ~_umask())
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=os.path.dirname(path))
    except OSError as e:  # name the path the user gave, not the temporary one
        raise OSError(e.errno, e.strerror, given) from None
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(e, OSError) and e.filename in (tmp, path) and e.errno is not None:
            raise OSError(e.errno, e.strerror, given) from None
        raise


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (flushed to disk before the rename)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def atomic_write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))
