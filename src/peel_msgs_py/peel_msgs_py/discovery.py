"""Where DDS traffic may go: this machine only, unless the user says otherwise.

ROS 2 Jazzy's ``ROS_AUTOMATIC_DISCOVERY_RANGE`` decides how far discovery reaches
(``LOCALHOST``, ``SUBNET`` -- the default of a stock install --, ``OFF``, ``SYSTEM_DEFAULT``);
``ROS_DOMAIN_ID`` (0-101, and 215-232) separates graphs that share a range. ``peel graph``,
``peel demo`` and the test suite set ``LOCALHOST`` unless the variable is already set, so that
nothing leaves the machine by default; docs/runtime.md says how to open it for deployment.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

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


def domain_for(pid: int, offset: int = 0) -> int:
    """A ROS domain for one test run, derived from a process id (``offset`` for the n-th graph
    of the run): in 31..100, valid for Fast DDS's port mapping and clear of the low domains
    people pick by hand."""
    return 31 + (pid * 7 + offset) % 70
