"""Single-threaded executor: every callback runs in the thread that spins, as in rclpy.

``spin_once`` executes at most one ready item -- one sample of a subscription, one request of
a service, one reply of a client, or one due timer -- taking them round-robin over all nodes.
While nothing is ready it blocks on a Cyclone DDS wait set holding a read condition per reader,
in slices of at most :data:`WAIT_SLICE_S` so that signals (Ctrl-C) are handled promptly, until
the next wall-clock timer is due. Timers on simulated time become due when a ``/clock`` sample
moves their clock, which wakes the wait set.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from cyclonedds.core import GuardCondition, WaitSet
from cyclonedds.util import duration

from .context import Context, ExternalShutdownException, get_default_context
from .services import Future

#: Longest single block in the wait set (s); bounds the latency of Ctrl-C and shutdown.
WAIT_SLICE_S = 0.05
#: Wait slice while a service holds replies for clients not yet matched (s).
PENDING_SLICE_S = 0.01


class SingleThreadedExecutor:
    """``rclpy.executors.SingleThreadedExecutor``."""

    def __init__(self, *, context: Context | None = None) -> None:
        self._context = context or get_default_context()
        self._nodes: list[Any] = []
        self._ws: WaitSet | None = None
        self._guard: GuardCondition | None = None
        self._attached_key: tuple[Any, ...] | None = None
        self._rr = 0

    @property
    def context(self) -> Context:
        return self._context

    def add_node(self, node: Any) -> bool:
        if node in self._nodes:
            return False
        if node._executor is not None and node._executor is not self:
            node._executor.remove_node(node)
        self._nodes.append(node)
        node._executor = self
        self.wake()
        return True

    def remove_node(self, node: Any) -> None:
        if node in self._nodes:
            self._nodes.remove(node)
            node._executor = None

    def get_nodes(self) -> list[Any]:
        return list(self._nodes)

    def wake(self) -> None:
        if self._guard is not None:
            self._guard.set(True)

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        for node in list(self._nodes):
            self.remove_node(node)
        self._ws = None
        self._guard = None
        return True

    # ------------------------------------------------------------------ internals
    def _waitables(self) -> list[Any]:
        items: list[Any] = []
        for node in self._nodes:
            items += node._subscriptions + node._services + node._clients + node._timers
        return items

    def _rebuild_waitset(self) -> None:
        key = tuple((n._uid, n.version) for n in self._nodes)
        if key == self._attached_key and self._ws is not None:
            return
        participant = self._context.participant
        ws = WaitSet(participant)
        self._guard = GuardCondition(participant)
        ws.attach(self._guard)
        for item in self._waitables():
            cond = getattr(item, "_cond", None)
            if cond is not None:
                ws.attach(cond)
        self._ws = ws
        self._attached_key = key

    def _next_work(self) -> Callable[[], None] | None:
        items = self._waitables()
        n = len(items)
        for k in range(n):
            item = items[(self._rr + k) % n]
            work = item._take_work()
            if work is not None:
                self._rr = (self._rr + k + 1) % max(n, 1)
                return work
        return None

    def _wait_budget(self) -> float:
        budget = WAIT_SLICE_S
        for node in self._nodes:
            if any(s._pending for s in node._services):
                budget = min(budget, PENDING_SLICE_S)
            for timer in node._timers:
                if timer.is_canceled() or timer._uses_sim_time:
                    continue
                left = timer.time_until_next_call()
                if left is not None:
                    budget = min(budget, max(left, 0) / 1e9)
        return budget

    def _check_context(self) -> None:
        if self._context.externally_shut_down:
            self._context.try_shutdown()
            raise ExternalShutdownException()

    # ------------------------------------------------------------------ spinning
    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Run one ready callback, waiting up to ``timeout_sec`` (None = forever) for one."""
        end = None if timeout_sec is None else time.monotonic() + max(timeout_sec, 0.0)
        while True:
            self._check_context()
            if not self._context.ok():
                return
            for node in self._nodes:
                for srv in node._services:
                    if srv._pending:
                        srv._flush()
            work = self._next_work()
            if work is not None:
                work()
                return
            self._rebuild_waitset()
            budget = self._wait_budget()
            if end is not None:
                left = end - time.monotonic()
                if left <= 0:
                    return
                budget = min(budget, left)
            if budget > 0:
                assert self._ws is not None
                self._ws.wait(duration(seconds=budget))
                if self._guard is not None:
                    self._guard.set(False)

    def spin(self) -> None:
        while self._context.ok() or self._context.externally_shut_down:
            self.spin_once(None if not self._nodes else WAIT_SLICE_S * 4)

    def spin_until_future_complete(self, future: Future, timeout_sec: float | None = None) -> None:
        end = None if timeout_sec is None else time.monotonic() + timeout_sec
        while not future.done() and (self._context.ok() or self._context.externally_shut_down):
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                return
            self.spin_once(left if left is not None else WAIT_SLICE_S * 4)

    def spin_once_until_future_complete(
        self, future: Future, timeout_sec: float | None = None
    ) -> None:
        if not future.done():
            self.spin_once(timeout_sec)


Executor = SingleThreadedExecutor
