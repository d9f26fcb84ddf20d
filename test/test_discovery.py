"""ROS domains claimed with a lock (peel_msgs_py.discovery.claim_domain): no two live claims on
one machine share a domain, a claim ends with its process, and the suite's own run holds one."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from peel_msgs_py import discovery

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

HOLDER = """
import sys
from peel_msgs_py import discovery
claim = discovery.claim_domain(int(sys.argv[1]))
print(claim.domain, flush=True)
sys.stdin.readline()  # hold it until told
"""


def test_two_claims_never_share_a_domain_and_a_released_one_is_free_again() -> None:
    a = discovery.claim_domain(10)
    b = discovery.claim_domain(10)  # same start: the next free one
    try:
        assert a.domain != b.domain
        assert {a.domain, b.domain} <= set(discovery.CLAIMABLE)
    finally:
        a.release()
        b.release()
    c = discovery.claim_domain(a.domain - discovery.CLAIMABLE.start)
    c.release()
    assert c.domain == a.domain


def test_a_claim_held_by_another_process_is_skipped_until_it_exits() -> None:
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, "20"], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        held = int(holder.stdout.readline())  # type: ignore[union-attr]
        mine = discovery.claim_domain(held - discovery.CLAIMABLE.start)
        mine.release()
        assert mine.domain != held
    finally:
        holder.communicate("\n", timeout=60)  # the holder exits: its lock goes with it
    again = discovery.claim_domain(held - discovery.CLAIMABLE.start)
    again.release()
    assert again.domain == held


def test_the_run_and_each_graph_test_hold_their_domains(ros_domain: str) -> None:
    run = int(os.environ[discovery.DOMAIN_VAR])
    assert run == int(ros_domain)  # the fixture set it for this test's children
    other = discovery.claim_domain(int(ros_domain) - discovery.CLAIMABLE.start)
    other.release()
    assert other.domain != int(ros_domain)  # held while the test runs
