"""Our lifecycle manager: managed nodes driven through their standard services (docs/graph.md
"Lifecycle").

Every managed node serves ``<node>/change_state`` (``lifecycle_msgs/srv/ChangeState``) and
``<node>/get_state`` (``lifecycle_msgs/srv/GetState``); :class:`Lifecycle` holds their clients
on any rclpy node (``peel graph``'s monitor, the ``peel lifecycle`` command's own node), asks
by transition label (``configure``, ``activate``, ``deactivate``, ``cleanup``, ``shutdown``)
and never blocks: a spin loop calls :meth:`Sequence.step` until it is done.

:class:`Sequence` runs waves of transitions: the requests of one wave go out together (as soon
as each node's service is there) and the next wave starts when all of them succeeded. The bring
up of a graph (:func:`bring_up`) is one wave configuring every node (model loads and simulator
builds overlap), then one activate per node in the given order (the planner before the bridge,
so the bridge's first sample finds a planner that answers). A refused transition (a failed
configure: the node's log names why) or a service that does not appear within ``timeout_s``
ends the sequence with :attr:`Sequence.error`; :attr:`Sequence.failed` names the nodes whose
configure failed, which ``peel graph`` shuts down (a finalized node exits with its error), and
:attr:`Sequence.late` the others that did not come up. :func:`drive` is the rclpy side of
``peel lifecycle`` (:mod:`.lifecycle_cli`).

**A lost answer is asked after.** A service's response can be lost while DDS discovery of a
fresh client is still under way (the server's response writer not yet matched to the client's
reader: ros2/rmw_fastrtps#390), seen here as a ``get_state`` of a
loaded CI machine that never answered. So a transition unanswered after :data:`PROBE_S` is
followed by ``get_state`` (again every :data:`PROBE_S` while unanswered; a node's
single-threaded executor answers it after the transition ran): the goal state counts as success,
the state the transition starts from as a lost request, sent again (at most :data:`SENDS` in
all). ``get_state`` alone is simply asked again.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import rclpy
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.client import Client
from rclpy.node import Node
from rclpy.task import Future
from rclpy.utilities import remove_ros_args as _remove_ros_args

from peel_msgs_py.lifecycle import FINALIZED, TRANSITIONS, goal_state

#: The node name of ``peel lifecycle`` (``peel_lifecycle_manager`` under the launch file).
NODE_NAME = "peel_lifecycle"
#: Seconds an unanswered request waits before ``get_state`` is asked (module docstring).
PROBE_S = 5.0
#: How many times one transition is sent at most (the first and the resends of a lost one).
SENDS = 3


def absolute(target: str) -> str:
    """``target``'s fully qualified name (a bare node name is in the root namespace)."""
    return target if target.startswith("/") else "/" + target


def service(target: str, name: str) -> str:
    """The name of ``target``'s lifecycle service ``name``."""
    return f"{absolute(target)}/{name}"


class Lifecycle:
    """``change_state`` / ``get_state`` clients of managed nodes on one rclpy node."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self._clients: dict[tuple[str, str], Client] = {}

    def client(self, target: str, kind: type) -> Client:
        name = "change_state" if kind is ChangeState else "get_state"
        key = (target, name)
        if key not in self._clients:
            self._clients[key] = self.node.create_client(kind, service(target, name))
        return self._clients[key]

    def ready(self, target: str) -> bool:
        """Both services of ``target`` are matched."""
        return all(self.client(target, k).service_is_ready() for k in (ChangeState, GetState))

    def change(self, target: str, transition: str) -> Future:
        """Ask ``target`` for ``transition`` (by label); the future's result has ``success``."""
        goal_state(transition)  # an unknown label is refused here, in one line
        req = ChangeState.Request()
        req.transition.label = transition
        return self.client(target, ChangeState).call_async(req)

    def state(self, target: str) -> Future:
        """Ask ``target`` for its state; the future's result has ``current_state.label``."""
        return self.client(target, GetState).call_async(GetState.Request())

    def close(self) -> None:
        for client in self._clients.values():
            self.node.destroy_client(client)
        self._clients.clear()


@dataclass
class Step:
    """One transition of one node in a wave, with the ``get_state`` that follows an answer not
    come within :data:`PROBE_S` (module docstring)."""

    target: str
    transition: str
    success: bool | None = None
    sent: list[Future] = field(default_factory=list)  # every change_state sent, in order
    asked_s: float = 0.0  # when the latest request (change_state or get_state) went out
    probe: Future | None = None

    @property
    def future(self) -> Future | None:
        """The latest change_state sent (None before the first)."""
        return self.sent[-1] if self.sent else None

    def send(self, lc: Lifecycle, now: float) -> None:
        self.sent.append(lc.change(self.target, self.transition))
        self.asked_s = now

    def advance(self, lc: Lifecycle, now: float) -> None:
        """Collect an answer; ask ``get_state`` after a silence; resend a lost request."""
        answers = [f.result() for f in self.sent if f.done()]
        if any(a is not None and a.success for a in answers):
            self.success = True
        elif self.future is not None and self.future.done():
            self.success = False  # refused (a resend only follows get_state's start state)
        elif self.probe is not None and self.probe.done():
            self._probed(lc, self.probe.result(), now)
        elif now - self.asked_s > PROBE_S:
            self.probe, self.asked_s = lc.state(self.target), now

    def _probed(self, lc: Lifecycle, result: Any, now: float) -> None:
        self.probe = None
        label = result.current_state.label if result is not None else None
        starts, goal = TRANSITIONS[self.transition]
        if label == goal:
            self.success = True  # it ran; its answer was lost
        elif label in starts and len(self.sent) < SENDS:
            self.send(lc, now)  # the request was lost


@dataclass
class Sequence:
    """Waves of transitions, advanced by :meth:`step` from a spin loop (module docstring)."""

    lc: Lifecycle
    waves: list[list[Step]]
    timeout_s: float
    error: str | None = None
    failed: list[str] = field(default_factory=list)
    #: the nodes whose service or answer did not come within ``timeout_s``, or that refused
    #: a transition other than configure
    late: list[str] = field(default_factory=list)
    results: list[Step] = field(default_factory=list)
    _since: float | None = None

    @property
    def done(self) -> bool:
        """Every wave succeeded, or one failed (:attr:`error`)."""
        return self.error is not None or not self.waves

    def step(self, now: float | None = None) -> None:
        """Send what can be sent, collect what came back, fail on the timeout."""
        now = time.monotonic() if now is None else now
        if self.done:
            return
        if self._since is None:
            self._since = now
        wave = self.waves[0]
        for s in wave:
            if s.future is None and self.lc.ready(s.target):
                s.send(self.lc, now)
            elif s.future is not None and s.success is None:
                s.advance(self.lc, now)
        self._check(wave, now)

    def _check(self, wave: list[Step], now: float) -> None:
        refused = [s for s in wave if s.success is False]
        if refused:
            self.failed = [s.target for s in refused if s.transition == "configure"]
            self.late = [s.target for s in refused if s.transition != "configure"]
            self.error = "; ".join(_refused(s) for s in refused)
            self.results += wave
            return
        if all(s.success for s in wave):
            self.results += self.waves.pop(0)
            self._since = now
            return
        assert self._since is not None
        if now - self._since > self.timeout_s:
            late = [s for s in wave if s.success is None]
            self.late = [s.target for s in late]
            self.error = "; ".join(_late(s, self.timeout_s) for s in late)


def _refused(s: Step) -> str:
    stays = "unconfigured" if s.transition == "configure" else "in its state"
    return f"{s.target}: {s.transition} failed (it stays {stays}; its log says why)"


def _late(s: Step, timeout_s: float) -> str:
    what = (f"answer to {s.transition}" if s.future is not None
            else f"{service(s.target, 'change_state')} service")
    return f"{s.target}: no {what} within {timeout_s:g} s"


def bring_up(lc: Lifecycle, targets: Iterable[str], timeout_s: float) -> Sequence:
    """Configure every node of ``targets`` at once, then activate them one by one in order."""
    names = list(targets)
    waves = [[Step(t, "configure") for t in names], *([Step(t, "activate")] for t in names)]
    return Sequence(lc, waves, timeout_s)


def transitions(lc: Lifecycle, transition: str, targets: Iterable[str],
                timeout_s: float) -> Sequence:
    """``transition`` on every node of ``targets`` at once."""
    return Sequence(lc, [[Step(t, transition) for t in targets]], timeout_s)


class GraphBringUp:
    """``peel graph``'s manager: :func:`bring_up` of ``targets`` stepped from the launcher's
    watch loop; a node whose configure failed is then shut down, so that it exits with its
    error (:meth:`~peel_msgs_py.ros.lifecycle.ManagedNode.exit_error`) and the launcher stops
    the graph as for any node that died."""

    def __init__(self, node: Node, targets: Iterable[str], timeout_s: float) -> None:
        self.lc = Lifecycle(node)
        self.seq = bring_up(self.lc, targets, timeout_s)
        self.reported = False

    @property
    def late(self) -> list[str]:
        """The nodes that did not come up (in time), other than those shut down."""
        return self.seq.late

    def step(self) -> str | None:
        """Advance the bring-up; the error line, once, when it failed."""
        self.seq.step()
        if self.seq.error is None or self.reported:
            return None
        self.reported = True
        for target in self.seq.failed:
            self.lc.change(target, "shutdown")
        return self.seq.error


# -- peel lifecycle (peel_bringup.lifecycle_cli) ------------------------------------------------
def remove_ros_args(argv: list[str]) -> list[str]:
    """``argv`` without the ROS arguments (``--ros-args ...``) ``ros2 launch`` appends."""
    return _remove_ros_args(["peel", *argv])[1:]


def _spin(node: Node, timeout_s: float) -> None:
    rclpy.spin_once(node, timeout_sec=timeout_s)


def spin_until(node: Node, seq: Sequence) -> None:
    """Spin ``node`` until ``seq`` is done."""
    while not seq.done:
        _spin(node, 0.05)
        seq.step()


def states(lc: Lifecycle, nodes: list[str], timeout_s: float) -> dict[str, str]:
    """Each node's state label by its full name (``unknown``: no answer within ``timeout_s``)."""
    futures: dict[str, Any] = {}
    asked: dict[str, float] = {}
    deadline = time.monotonic() + timeout_s
    while (now := time.monotonic()) < deadline:
        for n in nodes:
            lost = n in futures and not futures[n].done() and now - asked[n] > PROBE_S
            if (n not in futures and lc.ready(n)) or lost:
                futures[n], asked[n] = lc.state(n), now  # a lost answer: asked again
        if len(futures) == len(nodes) and all(f.done() for f in futures.values()):
            break
        _spin(lc.node, 0.05)
    out = {}
    for n in nodes:
        f = futures.get(n)
        result = f.result() if f is not None and f.done() else None
        out[absolute(n)] = result.current_state.label if result is not None else "unknown"
    return out


def drive(action: str, transition: str | None, nodes: list[str], timeout_s: float,
          argv: list[str]) -> dict[str, Any]:
    """``peel lifecycle ACTION``: the transitions asked (``up``: :func:`bring_up`; ``set``:
    ``transition`` on every node) and every node's state afterwards, as the report it prints."""
    rclpy.init(args=["peel", *argv])
    node = rclpy.create_node(NODE_NAME)
    lc = Lifecycle(node)
    try:
        report: dict[str, Any] = {"action": action}
        gone: list[str] = []
        if action != "get":
            assert action == "up" or transition is not None
            seq = (bring_up(lc, nodes, timeout_s) if action == "up"
                   else transitions(lc, str(transition), nodes, timeout_s))
            spin_until(node, seq)
            report["steps"] = [{"node": s.target, "transition": s.transition,
                                "success": bool(s.success)} for s in seq.results]
            report["error"] = seq.error
            gone = [s.target for s in seq.results if s.transition == "shutdown" and s.success]
        report["nodes"] = {**states(lc, [n for n in nodes if n not in gone], timeout_s),
                           **{absolute(n): FINALIZED for n in gone}}  # their processes end
        return report
    finally:
        lc.close()
        node.destroy_node()
        rclpy.try_shutdown()
