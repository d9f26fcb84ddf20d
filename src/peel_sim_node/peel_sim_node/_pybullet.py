"""Import pybullet without its "pybullet build time" banner on the terminal (CLI output and
one-line errors stay clean)."""

from __future__ import annotations

import os
import sys


def _quiet_import():  # type: ignore[no-untyped-def]
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    saved = []
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        devnull = os.open(os.devnull, os.O_WRONLY)
        for fd in (1, 2):
            saved.append((fd, os.dup(fd)))
            os.dup2(devnull, fd)
        os.close(devnull)
    except OSError:  # no redirectable stdio (best effort): the banner is merely printed
        pass
    try:
        import pybullet
    finally:
        for fd, old in saved:
            os.dup2(old, fd)
            os.close(old)
    return pybullet


pb = _quiet_import()
