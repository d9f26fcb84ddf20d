"""The managed-node lifecycle as plain data (no ROS; docs/graph.md "Lifecycle").

The planner and both plant bridges are ROS 2 managed nodes (REP-2002 / ``lifecycle_msgs``):
they start ``unconfigured`` and move through the standard transitions

* ``configure``: unconfigured -> inactive (parameters checked, the model loaded and warmed up,
  the simulator built, the controller connected and its HELLO checked);
* ``activate``: inactive -> active (commands flow);
* ``deactivate``: active -> inactive (the planner stops publishing, the bridges stop
  forwarding; the Nachi bridge sends STOP to a running task);
* ``cleanup``: inactive -> unconfigured (everything configure built released);
* ``shutdown``: any of the three -> finalized (released as by cleanup).

A configure that fails leaves the node ``unconfigured``; its reason is one line,
:class:`ConfigureError`. :data:`AUTOSTART` (``node.autostart``) lets a node run its own
configure and activate at start, for a node started by hand without a lifecycle manager.
"""

from __future__ import annotations

from .errors import PeelError
from .params import ParamSpec

#: Primary states, as ``lifecycle_msgs/msg/State`` labels them.
UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = "unconfigured", "inactive", "active", "finalized"

#: Transition label -> (the states it starts from, the state it ends in on success).
TRANSITIONS: dict[str, tuple[tuple[str, ...], str]] = {
    "configure": ((UNCONFIGURED,), INACTIVE),
    "activate": ((INACTIVE,), ACTIVE),
    "deactivate": ((ACTIVE,), INACTIVE),
    "cleanup": ((INACTIVE,), UNCONFIGURED),
    "shutdown": ((UNCONFIGURED, INACTIVE, ACTIVE), FINALIZED),
}

#: Exit status of an autostarted node whose configure failed on bad input (a parameter, a model).
BAD_INPUT = 2

AUTOSTART = ParamSpec(
    "node.autostart", bool, True,
    "configure and activate at start, without a lifecycle manager (a failed configure then "
    "ends the node); false: start unconfigured and wait for change_state (peel graph and the "
    "launch file set false and drive the transitions)")


class ConfigureError(PeelError):
    """Why ``configure`` cannot succeed, in one line. ``exit_status`` is the status of an
    autostarted node that stops on it (2: bad input; 1: an outside party, e.g. no controller)."""

    def __init__(self, message: str, exit_status: int = BAD_INPUT) -> None:
        super().__init__(message)
        self.exit_status = exit_status


def goal_state(transition: str) -> str:
    """The state ``transition`` ends in on success; PeelError naming the known ones."""
    if transition not in TRANSITIONS:
        raise PeelError(f"unknown lifecycle transition {transition!r}; one of "
                        f"{', '.join(TRANSITIONS)}")
    return TRANSITIONS[transition][1]
