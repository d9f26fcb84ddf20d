"""The order in which a learner that serves several cells learns their finished tasks, and the
names of the cells and of their updates (no ROS; the rclpy side: :mod:`~model_learner_node.cells_node`).

Algorithm 1 runs on one pooled replay (3.3.1): every cell's finished peels go into the same
pool, and each update starts from the weights the previous one left. What an update learns
therefore depends on the order of the updates, and the cells finish in a wall-clock order
that no seed fixes. :class:`TaskOrder` takes the trajectories as they arrive and hands them
to the worker in the order of the key ``(task k, position of the cell in node.cells)``:
every cell's task 1 in the order of the list, then every cell's task 2, and so on.

The key is taken as soon as no smaller one can still come: a cell *owes* the task after the
last one of it that was learned; a smaller owed key holds a pending one back for at most
``wait_s`` (wall s) after the pending one arrived. A cell that misses that wait is *late*:
it holds nobody up again until its trajectory arrives, and that one is learned as soon as it
is the smallest pending key. So the order (and with a seed, every update: Algorithm 1's slice
sampling is seeded per update index) depends only on the seeds, ``node.cells`` and each
trajectory's task index, as long as every cell delivers each task within ``wait_s`` of the
first cell that could go before it; a cell that is down or slower than that is learned from
when its peel arrives, and that arrival, counted in updates, is then what the order depends on.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from peel_msgs_py.errors import PeelError

_NAMESPACE_RE = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")


def check_cells(names: Sequence[str]) -> None:
    """``node.cells`` holds absolute namespaces (``/cell_0``), each once; else PeelError."""
    bad = [n for n in names if not _NAMESPACE_RE.fullmatch(n)]
    if bad:
        raise PeelError(f"parameter 'node.cells': {bad[0]!r} is not an absolute namespace "
                        f"such as '/cell_0'")
    if len(set(names)) != len(names):
        raise PeelError(f"parameter 'node.cells': a cell is named twice in {list(names)}")


def cell_producer(learner: str, cell: str) -> str:
    """The producer name of an update learned from a task of ``cell``: ``learner@cell``."""
    return f"{learner}@{cell}"


@dataclass
class TaskOrder:
    """A queue of ``(cell, task, item)`` taken in the order of the module docstring.

    ``get()`` blocks until an item is due (or ``None`` after :meth:`put(None) <put>`);
    ``add(cell, task, item)`` is called from the subscription callbacks."""

    cells: Sequence[str]
    wait_s: float
    clock: Any = time.monotonic
    _pending: dict[tuple[int, int], tuple[Any, float]] = field(default_factory=dict)
    _learned: dict[int, int] = field(default_factory=dict)  # cell index -> last task learned
    _late: set[int] = field(default_factory=set)
    _closed: bool = False
    _cv: threading.Condition = field(default_factory=threading.Condition)

    def add(self, cell: str, task: int, item: Any) -> None:
        """A finished ``task`` (1-based) of ``cell``; a repeated key replaces the earlier item."""
        index = list(self.cells).index(cell)
        with self._cv:
            self._pending[(task, index)] = (item, self.clock())
            self._late.discard(index)
            self._cv.notify_all()

    def learned(self, cell: str, task: int) -> None:
        """``task`` of ``cell`` was learned before (a restarted learner's dropped one): the
        cell owes the task after it, so nobody waits for this one."""
        index = list(self.cells).index(cell)
        with self._cv:
            self._learned[index] = max(self._learned.get(index, 0), task)
            self._cv.notify_all()

    def put(self, item: None) -> None:
        """``put(None)``: stop; ``get`` returns None from now on (the node's worker protocol)."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()

    def qsize(self) -> int:
        with self._cv:
            return len(self._pending)

    def owed(self, index: int) -> tuple[int, int]:
        """The key cell ``index`` delivers next: the task after its last learned one."""
        return (self._learned.get(index, 0) + 1, index)

    def due(self) -> tuple[tuple[int, int] | None, float | None]:
        """The key to take now (or None) and, when one is held back, how long to wait for it."""
        if not self._pending:
            return None, None
        key = min(self._pending)
        waiting = [self.owed(i) for i in range(len(self.cells))
                   if i not in self._late and self.owed(i) < key and self.owed(i) not in
                   self._pending]
        if not waiting:
            return key, None
        left = self._pending[key][1] + self.wait_s - self.clock()
        if left > 0:
            return None, left
        self._late.update(i for _, i in waiting)
        return key, None

    def get(self) -> tuple[str, int, Any] | None:
        """The next ``(cell, task, item)`` in order; None once stopped."""
        with self._cv:
            while not self._closed:
                key, left = self.due()
                if key is not None:
                    item, _ = self._pending.pop(key)
                    task, index = key
                    self._learned[index] = max(self._learned.get(index, 0), task)
                    return self.cells[index], task, item
                self._cv.wait(timeout=left)
            return None
