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

from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped

from peel_msgs_py import codec, topics
from peel_msgs_py.errors import PeelError
from peel_msgs_py.ros.messages import stamp_ns
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.units import m_to_mm, mps_to_mmps
from peel_msgs_py.wire import DropLog

from .in_peel import InPeel


class InPeelTopics:
    """The sample subscriptions and the fast-step thread of the learner node (module doc)."""

    def __init__(self, node: Any, in_peel: InPeel, lock: threading.Lock,
                 swap: Callable[[Path], tuple[bool, str]], closing: threading.Event) -> None:
        self.node, self.in_peel, self.lock, self.swap, self.closing = (
            node, in_peel, lock, swap, closing)
        qos = topics.qos_profile
        node.create_subscription(WrenchStamped, topics.WRENCH, self.on_wrench,
                                 qos(topics.WRENCH, subscriber=True))
        node.create_subscription(TwistStamped, topics.TWIST, self.on_twist,
                                 qos(topics.TWIST, subscriber=True))
        node.create_subscription(PoseStamped, topics.POSE, self.on_pose,
                                 qos(topics.POSE, subscriber=True))
        self.drops = DropLog()
        self.pending: queue.Queue[Trajectory | None] = queue.Queue(maxsize=1)
        self.thread = threading.Thread(target=self.work, name="fast_step", daemon=True)
        self.thread.start()

    def on_wrench(self, msg: WrenchStamped) -> None:
        self.on_part(msg, topics.WRENCH, fx_n=msg.wrench.force.x, fz_n=msg.wrench.force.z)

    def on_twist(self, msg: TwistStamped) -> None:
        self.on_part(msg, topics.TWIST, v_mmps=mps_to_mmps(msg.twist.linear.x))

    def on_pose(self, msg: PoseStamped) -> None:
        self.on_part(msg, topics.POSE, q_mm=m_to_mm(msg.pose.position.x))

    def on_part(self, msg: Any, topic: str, **parts: float) -> None:
        if self.closing.is_set():
            return
        try:
            task = codec.task_from_frame_id(msg.header.frame_id)
        except PeelError as exc:
            line = self.drops.drop(topic, "header.frame_id", f"is bad: {exc}")
            if line is not None:
                self.node.get_logger().warn(line)
            return
        running = self.in_peel.add(stamp_ns(msg.header.stamp), task, **parts)
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
