"""The recorder node: subscribes to the /peel topics and /clock and writes them to an MCAP bag.

Written against rclpy's API through :mod:`peel_msgs_py.runtime`, so it runs on a Jazzy machine
(rclpy) and on the embedded Cyclone DDS runtime alike. Each topic of the table
(:mod:`peel_msgs_py.topics`) is subscribed with the profile its publishers offer (``/clock``
best effort, latched topics transient local so their current value is recorded) and every
message is stored as CDR bytes with the wall-clock receive time (``time.time_ns()``), as
``ros2 bag record`` does without ``--use-sim-time``. Chunks are flushed by size and by age
(:class:`~peel_msgs_py.bag.BagWriter`); a timer ticks the writer so that a quiet topic's open
chunk still reaches the disk within ``flush_interval_s``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from functools import partial
from typing import Any

from .bag import BagWriter
from .runtime import Node
from .runtime.msg import get_message_class, serialize
from .topics import qos_profile, topic

NODE_NAME = "peel_recorder"
#: Period of the writer tick (s): time-based chunk flushes and metadata refreshes.
TICK_PERIOD_S = 0.2


class RecorderNode(Node):  # type: ignore[misc, valid-type]
    """Records ``topics`` into an open :class:`BagWriter`."""

    def __init__(self, writer: BagWriter, topics: Sequence[str], *, name: str = NODE_NAME) -> None:
        super().__init__(name)
        self.writer = writer
        self.received = 0
        self._subs: list[Any] = []
        for name_ in topics:
            spec = topic(name_)
            cls = get_message_class(spec.type)
            writer.add_topic(spec.name, spec.type, [spec.qos])
            self._subs.append(
                self.create_subscription(
                    cls, spec.name, partial(self._on_message, spec.name),
                    qos_profile(spec, subscriber=True),
                )
            )
        self._timer = self.create_timer(TICK_PERIOD_S, self.writer.tick)

    def _on_message(self, topic_name: str, msg: Any) -> None:
        self.writer.write(topic_name, serialize(msg), time.time_ns())
        self.received += 1


def main(argv: list[str] | None = None) -> int:
    """Console script for ``ros2 run``: same options as ``peel record`` (``--ros-args`` ignored)."""
    import sys

    from .recorder_cli import run

    args = list(sys.argv[1:] if argv is None else argv)
    if "--ros-args" in args:
        args = args[: args.index("--ros-args")]
    return run(args)


if __name__ == "__main__":
    import sys

    sys.exit(main())
