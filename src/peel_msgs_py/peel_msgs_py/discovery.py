"""Where DDS traffic may go: this machine only, unless the user says otherwise.

ROS 2 Jazzy's ``ROS_AUTOMATIC_DISCOVERY_RANGE`` decides how far discovery reaches
(``LOCALHOST``, ``SUBNET`` -- the default of a stock install --, ``OFF``, ``SYSTEM_DEFAULT``);
``ROS_DOMAIN_ID`` (0-101, and 215-232) separates graphs that share a range. ``peel graph``,
``peel demo`` and the test suite set ``LOCALHOST`` unless the variable is already set, so that
nothing leaves the machine by default; docs/runtime.md says how to open it for deployment.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

RANGE_VAR = "ROS_AUTOMATIC_DISCOVERY_RANGE"
DOMAIN_VAR = "ROS_DOMAIN_ID"
LOCALHOST = "LOCALHOST"


def confine(env: MutableMapping[str, str] | None = None) -> MutableMapping[str, str]:
    """Set ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` in ``env`` (default ``os.environ``)
    unless it is set already; returns ``env``."""
    env = os.environ if env is None else env
    if not env.get(RANGE_VAR):
        env[RANGE_VAR] = LOCALHOST
    return env


#: Domains :func:`claim_domain` hands out (clear of the low ones people pick by hand).
CLAIMABLE = range(31, 101)


class DomainClaim:
    """One ROS domain held for this process: an exclusive ``flock`` on
    ``<tmp>/peel-ros-domains/<domain>.lock``, released by :meth:`release` or when the process
    ends (however it ends), so no two live claims on one machine share a domain."""

    def __init__(self, domain: int, fd: int) -> None:
        self.domain, self._fd = domain, fd

    def release(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)  # closing the descriptor drops the lock
            self._fd = -1


def lock_dir() -> Path:
    """Where the domain locks live (one machine, every user of it)."""
    path = Path(tempfile.gettempdir()) / "peel-ros-domains"
    path.mkdir(mode=0o777, exist_ok=True)
    return path


def claim_domain(start: int = 0) -> DomainClaim:
    """The first free domain of :data:`CLAIMABLE`, trying from ``start`` (e.g. derived from the
    process id, so that concurrent runs seldom try the same ones first); raises ``RuntimeError``
    when every domain is held."""
    folder = lock_dir()
    n = len(CLAIMABLE)
    for i in range(n):
        domain = CLAIMABLE[(start + i) % n]
        fd = os.open(folder / f"{domain}.lock", os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        with contextlib.suppress(OSError):
            os.set_inheritable(fd, False)  # children must not keep the domain after we release it
        return DomainClaim(domain, fd)
    raise RuntimeError(f"every ROS domain {CLAIMABLE.start}-{CLAIMABLE.stop - 1} is held by a "
                       f"live process on this machine (locks in {folder})")
