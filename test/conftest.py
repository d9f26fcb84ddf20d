"""Every test run on a ROS domain of its own, on this machine only (docs/runtime.md).

``ROS_DOMAIN_ID`` is derived from this pytest process's pid
(:func:`peel_msgs_py.discovery.domain_for`), so two runs on one machine (two worktrees, CI beside
a developer) never see each other's graphs; ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is LOCALHOST
unless the user set it, so nothing leaves the machine. Child processes inherit both. The
``ros_domain`` fixture gives a test that starts a graph a domain of its own within the run.
"""

from __future__ import annotations

import itertools
import os

import pytest

from peel_msgs_py import discovery

discovery.confine()
os.environ[discovery.DOMAIN_VAR] = str(discovery.domain_for(os.getpid()))
_offsets = itertools.count(1)


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> str:
    """A ROS domain for this test alone (set in the environment its children inherit)."""
    domain = str(discovery.domain_for(os.getpid(), next(_offsets)))
    monkeypatch.setenv(discovery.DOMAIN_VAR, domain)
    return domain


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test that takes a ROS domain of its own starts a graph: it must be marked ``process``
    so that ``scripts/flaky.sh`` repeats it."""
    unmarked = [it.nodeid for it in items
                if "ros_domain" in getattr(it, "fixturenames", ()) and "process" not in it.keywords]
    if unmarked:
        raise pytest.UsageError("tests with a ros_domain but no 'process' mark: " + ", ".join(unmarked))
