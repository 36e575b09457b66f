"""Atomic file writes, shared by every command that writes a file (datasets, policies, plots,
JSON): write a temporary file in the target's directory, give it the usual permissions, then
rename it onto the target. An error or an interrupt (Ctrl-C) leaves no partial file behind.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text"]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path, suffix: str | None = None) -> Iterator[str]:
    """Yield a temporary path beside ``path``; write it inside the ``with`` block.

    On a normal exit the file gets permissions ``0666 & ~umask`` (``mkstemp`` makes 0600) and
    replaces ``path``; on any exception it is removed and the exception propagates. ``suffix``
    (default: ``path``'s extension) lets writers that pick a format from the name (matplotlib,
    Pillow) see the right one.
    """
    path = os.fspath(path)
    if suffix is None:
        suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix,
                               dir=os.path.dirname(os.path.abspath(path)))
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
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
