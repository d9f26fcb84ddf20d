"""The learner's task order over several cells (``model_learner_node.cells``, docs/fleet.md) and
the check of ``node.cells``: every cell's task k in the order of the list before any task k+1,
whatever order they arrive in; a missing earlier task holds a later one back for ``wait_s``
only, after which its cell is late and holds nobody up again. No ROS (a fake clock)."""

from __future__ import annotations

import pytest

from model_learner_node.cells import TaskOrder, cell_producer, check_cells
from peel_msgs_py.errors import PeelError

CELLS = ("/cell_0", "/cell_1", "/cell_2")


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _take(order: TaskOrder) -> tuple[str, int] | None:
    key, _ = order.due()
    if key is None:
        return None
    cell, task, _ = order.get()
    return cell, task


def test_arrival_order_does_not_change_the_learning_order() -> None:
    for arrivals in ([2, 0, 1], [1, 2, 0], [0, 1, 2]):
        order = TaskOrder(CELLS, wait_s=30.0, clock=Clock())
        taken = []
        for task in (1, 2):
            for i in arrivals:
                order.add(CELLS[i], task, f"{CELLS[i]}:{task}")
                while (got := _take(order)) is not None:
                    taken.append(got)
        assert taken == [(c, t) for t in (1, 2) for c in CELLS], arrivals


def test_a_missing_cell_holds_the_others_back_once_for_wait_s() -> None:
    clock = Clock()
    order = TaskOrder(CELLS[:2], wait_s=10.0, clock=clock)
    order.add("/cell_1", 1, "b1")
    key, left = order.due()
    assert key is None and left == pytest.approx(10.0)  # /cell_0's task 1 may still come
    clock.now = 10.5
    assert _take(order) == ("/cell_1", 1)  # waited out: /cell_0 is late
    order.add("/cell_1", 2, "b2")
    assert _take(order) == ("/cell_1", 2)  # a late cell holds nobody up again
    order.add("/cell_0", 1, "a1")  # it comes back: its task is the smallest pending key
    order.add("/cell_1", 3, "b3")
    assert _take(order) == ("/cell_0", 1)
    key, left = order.due()  # and it is awaited again: its task 2 comes before task 3
    assert key is None and left is not None


def test_a_task_learned_before_a_restart_is_owed_by_nobody() -> None:
    order = TaskOrder(CELLS[:2], wait_s=30.0, clock=Clock())
    order.learned("/cell_0", 1)  # a restarted learner dropped both cells' task 1
    order.add("/cell_0", 2, "a2")
    key, left = order.due()
    assert key is None and left == pytest.approx(30.0)  # /cell_1's task 1 is still owed
    order.learned("/cell_1", 1)
    assert _take(order) == ("/cell_0", 2)  # at once: nobody owes an earlier key


def test_get_returns_none_once_stopped() -> None:
    order = TaskOrder(CELLS, wait_s=1.0)
    order.put(None)
    assert order.get() is None


def test_cells_are_absolute_namespaces_named_once() -> None:
    check_cells(["/cell_0", "/line_a/cell_1"])
    for bad in (["cell_0"], ["/cell 0"], ["/cell_0", "/cell_0"], ["/"]):
        with pytest.raises(PeelError, match="node\\.cells"):
            check_cells(bad)
    assert cell_producer("/model_learner_node", "/cell_1") == "/model_learner_node@/cell_1"
