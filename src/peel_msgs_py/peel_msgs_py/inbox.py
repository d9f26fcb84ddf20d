"""The reports a node takes from the wire, decoded and checked where they enter (no ROS).

A finished trajectory (``/peel/trajectory``), the planner's model record (``/peel/model_info``)
and the learner's update report (``/peel/model_update``) arrive as ``std_msgs`` messages. Each
decoder here returns the report or raises :class:`Refused` naming the field and the reason;
:func:`take` turns a refusal into a counted, rate-limited drop (:class:`~.wire.DropLog`), so
every node that listens drops the same messages for the same words.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from . import codec
from .errors import PeelError
from .modelinfo import ModelRecord, UpdateReport
from .trajectory import Trajectory
from .wire import DropLog, trajectory_nonfinite

T = TypeVar("T")


class Refused(PeelError):
    """A message that does not decode: ``name`` is the field, ``why`` the reason."""

    def __init__(self, name: str, why: str) -> None:
        super().__init__(f"{name} {why}")
        self.name, self.why = name, why


def trajectory(msg: Any) -> Trajectory:
    """A ``Float64MultiArray`` as a :class:`Trajectory` whose arrays are all finite."""
    try:
        traj = codec.trajectory_from_msg(msg)
    except PeelError as exc:
        raise Refused("layout", f"does not decode: {exc}") from None
    bad = trajectory_nonfinite(traj)
    if bad is not None:
        raise Refused(f"'{bad}'", "holds non-finite values")
    return traj


def model_record(msg: Any) -> ModelRecord:
    """A ``String`` as the planner's :class:`ModelRecord`."""
    try:
        return ModelRecord.from_json(msg.data)
    except PeelError as exc:
        raise Refused("data", f"is not a model record: {exc}") from None


def update_report(msg: Any) -> UpdateReport:
    """A ``String`` as the learner's :class:`UpdateReport`."""
    try:
        return UpdateReport.from_json(msg.data)
    except PeelError as exc:
        raise Refused("data", f"is not an update report: {exc}") from None


def take(drops: DropLog, topic: str, decode: Callable[[Any], T], msg: Any,
         log: Callable[[str], None]) -> T | None:
    """``decode(msg)``, or None after counting the refusal in ``drops`` (and passing its line
    to ``log`` when one is due)."""
    try:
        return decode(msg)
    except Refused as exc:
        line = drops.drop(topic, exc.name, exc.why)
        if line is not None:
            log(line)
        return None
