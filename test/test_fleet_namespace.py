"""The namespaced graph (docs/fleet.md): a cell without a namespace publishes exactly the topic
table's names, and a cell started with ``--ros-args -r __ns:=/cell_a`` has every topic under
``/cell_a`` and none anywhere else, side by side on one ROS domain.

Real node processes (the simulator bridge and the planner of each cell) on rclpy; an outside
rclpy node lists the topics. The bridges wait for more trajectory readers than there are, so
no task runs: the names exist from the nodes' construction.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator

import pytest
import rclpy
from graph_helpers import node_env

from peel_msgs_py import topics

pytestmark = pytest.mark.process  # starts processes: scripts/flaky.sh

#: ROS's own topics every node has (rosout, parameter events) and the global /diagnostics.
STANDARD = {"/rosout", "/parameter_events", topics.DIAGNOSTICS}
NODES = ("peel_sim_node", "peel_planner_node")
#: The planner's standard parameter service moves with its cell too.
SERVICES = {"/peel_planner_node/set_parameters", "/cell_a/peel_planner_node/set_parameters"}
WAIT_S = 120.0  # only a hang reaches it: two cells import torch on a loaded 2-core machine


def _start(name: str, namespace: str | None) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", f"{name}.node", "--ros-args", "-p", "use_sim_time:=true"]
    if name == "peel_sim_node":
        cmd += ["-p", "node.tasks:=1", "-p", "node.min_traj_subscribers:=50"]
    if namespace is not None:
        cmd += ["-r", f"__ns:={namespace}"]
    return subprocess.Popen(cmd, env=node_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


@pytest.fixture
def cells(ros_domain: str) -> Iterator[None]:
    procs = [_start(n, ns) for ns in (None, "/cell_a") for n in NODES]
    try:
        yield
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=30)


def _node_topics(node: rclpy.node.Node, name: str, namespace: str) -> set[str]:
    """Topics of node ``namespace/name`` (publishers and subscriptions), without ROS's own
    (and a managed node's ``<node>/transition_event``, which moves with the node's name)."""
    pubs = node.get_publisher_names_and_types_by_node(name, namespace)
    subs = node.get_subscriber_names_and_types_by_node(name, namespace)
    own = f"{namespace.rstrip('/')}/{name}/transition_event"
    return {t for t, _ in (*pubs, *subs)} - STANDARD - {own}


def _listing(node: rclpy.node.Node) -> dict[tuple[str, str], set[str]]:
    """(name, namespace) -> topics of each node of both cells, once discovery shows every
    node and every topic of the table in both places (waited for; only a hang times out)."""
    want = set(topics.TOPICS) | {topics.under("/cell_a", n) for n in topics.TOPICS}
    nodes = [(n, ns) for ns in ("/", "/cell_a") for n in NODES]
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.2)
        if not set(nodes) <= set(node.get_node_names_and_namespaces()):
            continue
        try:
            found = {key: _node_topics(node, *key) for key in nodes}
        except rclpy.node.NodeNameNonExistentError:
            continue
        services = {s for s, _ in node.get_service_names_and_types()}
        if set().union(*found.values()) == want and services >= SERVICES:
            return found
    raise AssertionError(f"after {WAIT_S:g} s: nodes {node.get_node_names_and_namespaces()}, "
                         f"topics {sorted(t for t, _ in node.get_topic_names_and_types())}")


def test_a_namespace_moves_the_whole_cell_and_none_keeps_the_table_names(cells: None) -> None:
    rclpy.init()
    node = rclpy.create_node("peel_test_lister")
    try:
        found = _listing(node)
        table = set(topics.TOPICS)
        seen = {t for t, _ in node.get_topic_names_and_types()} - STANDARD
        events = {f"{ns}/{n}/transition_event" for ns in ("", "/cell_a") for n in NODES}
        assert seen == table | {topics.under("/cell_a", n) for n in table} | events
        for name in NODES:  # each node's own endpoints: its cell's names, nowhere else
            root, moved = found[(name, "/")], found[(name, "/cell_a")]
            assert root and root <= table, (name, root)
            assert all(t.startswith("/cell_a/") for t in moved), (name, moved)
        assert {s for s, _ in node.get_service_names_and_types()} >= SERVICES
    finally:
        node.destroy_node()
        rclpy.shutdown()
