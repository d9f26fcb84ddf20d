"""The learner node's fast step inside the peel on rclpy: the per-sample subscriptions and the
fast-step thread (the ROS-free work is :class:`~model_learner_node.in_peel.InPeel`).

``/peel/wrench``, ``/peel/twist`` and ``/peel/pose`` (SI; converted by
:mod:`peel_msgs_py.units`) feed the running task; when a fast step is due the task so far goes
to the thread (a newer one replaces a copy not yet taken, so the thread never falls behind the
plant), which takes the step under the node's lock and asks the planner to swap an accepted fast
model in over its standard parameter service, the same request as an update between peels.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from peel_msgs_py.ros.state_topics import StateTopics
from peel_msgs_py.trajectory import Trajectory

from .in_peel import InPeel


class InPeelTopics:
    """The sample subscriptions and the fast-step thread of the learner node (module doc)."""

    def __init__(self, node: Any, in_peel: InPeel, lock: threading.Lock,
                 swap: Callable[[Path], tuple[bool, str]], closing: threading.Event) -> None:
        self.node, self.in_peel, self.lock, self.swap, self.closing = (
            node, in_peel, lock, swap, closing)
        self.state_topics = StateTopics(node, self.on_part, lambda: not closing.is_set())
        self.state_topics.subscribe()
        self.pending: queue.Queue[Trajectory | None] = queue.Queue(maxsize=1)
        self.thread = threading.Thread(target=self.work, name="fast_step", daemon=True)
        self.thread.start()

    def on_part(self, stamp_ns: int, task: int, parts: dict[str, float]) -> None:
        """One checked part of a state sample (:class:`StateTopics`)."""
        running = self.in_peel.add(stamp_ns, task, **parts)
        if running is None:
            return
        with contextlib.suppress(queue.Empty):  # a copy not taken yet is out of date
            self.pending.get_nowait()
        self.pending.put_nowait(running)

    def end_task(self, index: int) -> None:
        """Task ``index`` (0-based) has finished: none of its fast steps is offered any more."""
        self.in_peel.end_task(index)

    def work(self) -> None:
        """The fast-step thread: step, and swap an accepted fast model in while its task runs."""
        log = self.node.get_logger()
        while (running := self.pending.get()) is not None and not self.closing.is_set():
            with self.lock:
                result, path = self.in_peel.step(running)
                if result is None:
                    continue
                line = (f"task {result.task}: fast step {result.step} on samples "
                        f"[0, {result.fit_end}), one-step error {result.error_fast_n:.3f} N on "
                        f"[{result.fit_end}, {result.n_samples}) against {result.error_in_use_n:.3f}"
                        f" N in use, {result.fast_s:.2f} s")
                if not result.accepted:
                    log.info(f"{line}: not used (not better than the model in use)")
                    continue
                if path is None or not self.in_peel.current(result):
                    log.info(f"{line}: its task ended first, not offered")
                    continue
                ok, reason = self.swap(path)
                if self.closing.is_set():
                    return
                log.info(f"{line}: the planner swapped in {path.name}" if ok else
                         f"{line}: the planner refused {path.name}: {reason}")

    def stop(self) -> None:
        """End the thread (it finishes a running step, offers nothing more)."""
        with contextlib.suppress(queue.Empty):
            self.pending.get_nowait()
        self.pending.put(None)
