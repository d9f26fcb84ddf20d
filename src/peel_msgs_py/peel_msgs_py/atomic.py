"""Atomic file replacement: a half-written file never replaces a good one.

Every writer of a result file (checkpoints, dataset shards, bag metadata, reports, figures) goes
through :func:`atomic_write`: the content is written to a temporary file in the destination's
directory, flushed to disk, and moved onto the destination with :func:`os.replace` (atomic on
POSIX within one file system). If writing fails, the temporary file is removed and the previous
file, if any, is untouched.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], None]) -> Path:
    """Call ``write(tmp_path)``, fsync the result and move it onto ``path``; returns ``path``.

    The temporary file keeps ``path``'s suffix so writers that infer a format from it
    (``matplotlib.savefig``) work, and gets the permissions of a normally created file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix or ".tmp",
                               dir=path.parent)
    os.close(fd)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        write(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Atomically replace ``path`` with ``data``."""
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Atomically replace ``path`` with ``text`` (UTF-8)."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
