"""Every test run on a ROS domain of its own, on this machine only (docs/runtime.md).

``ROS_DOMAIN_ID`` is claimed for this pytest process, and each ``ros_domain`` of a test too,
with a lock per domain that a live process holds (:func:`peel_msgs_py.discovery.claim_domain`),
so two runs on one machine (two worktrees, CI beside a developer) never share a domain and never
see each other's graphs; ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is LOCALHOST
unless the user set it, so nothing leaves the machine. Child processes inherit both. The
``ros_domain`` fixture gives a test that starts a graph a domain of its own within the run.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator

import pytest

from peel_msgs_py import discovery

discovery.confine()
_RUN = discovery.claim_domain(os.getpid() * 7)  # held until this process ends
os.environ[discovery.DOMAIN_VAR] = str(_RUN.domain)
_offsets = itertools.count(1)  # each test tries a new domain first: a last test's stragglers


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A ROS domain for this test alone (set in the environment its children inherit), held
    from the test's start to its end."""
    claim = discovery.claim_domain(os.getpid() * 7 + next(_offsets))
    monkeypatch.setenv(discovery.DOMAIN_VAR, str(claim.domain))
    try:
        yield str(claim.domain)
    finally:
        claim.release()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test that takes a ROS domain of its own starts a graph: it must be marked ``process``
    so that ``scripts/flaky.sh`` repeats it."""
    unmarked = [it.nodeid for it in items
                if "ros_domain" in getattr(it, "fixturenames", ()) and "process" not in it.keywords]
    if unmarked:
        raise pytest.UsageError("tests with a ros_domain but no 'process' mark: " + ", ".join(unmarked))
