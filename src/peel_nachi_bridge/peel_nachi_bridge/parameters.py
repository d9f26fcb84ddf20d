"""Every parameter ``peel_nachi_bridge`` declares, as plain data (no ROS): where the controller
is and how the link recovers (``link.*``), the link's safety rules (``safety.*``,
docs/nachi_protocol.md) and the task sequence (``node.*``, the same names and meanings as
``peel_sim_node``'s; docs/graph.md). Units are in the names; every timeout is wall time on the
bridge's machine, times on the line are the controller's.

Registered under the ``peel.parameters`` entry point, so every parameter file naming this node is
checked against it (:func:`peel_msgs_py.params.load_param_file`). All of them are read-only at
run time: the link and the task sequence are fixed when the node starts. The physical task
(q_ter, t_max, the substrates) is the controller's, not the bridge's.
"""

from __future__ import annotations

from peel_bridge.parameters import LOOP_SPECS
from peel_bridge.slowdown import slowdown_specs
from peel_msgs_py.lifecycle import AUTOSTART
from peel_msgs_py.params import USE_SIM_TIME, ParamSpec
from peel_msgs_py.wire import speed_limit_specs

NODE_NAME = "peel_nachi_bridge"

#: ``link:``: the controller and the reconnect backoff.
LINK_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("link.host", str, "127.0.0.1", "controller address (IPv4 or host name)"),
    ParamSpec("link.port", int, 48100, "controller TCP port (NACHI-PEEL 1 default 48100)",
              min=1, max=65535),
    ParamSpec("link.connect_timeout_s", float, 2.0, "wall s for the TCP connect", min=0.01),
    ParamSpec("link.hello_timeout_s", float, 2.0, "wall s for HELLO after the connect", min=0.01),
    ParamSpec("link.reply_timeout_s", float, 1.0, "wall s for OK START and PONG", min=0.01),
    ParamSpec("link.ping_interval_s", float, 1.0, "wall s between PINGs while idle", min=0.05),
    ParamSpec("link.backoff_initial_s", float, 0.2, "first reconnect delay, wall s", min=0.01),
    ParamSpec("link.backoff_max_s", float, 5.0,
              "longest reconnect delay, wall s (>= link.backoff_initial_s)", min=0.01),
    ParamSpec("link.backoff_factor", float, 2.0, "delay growth per failed attempt", min=1.0),
    ParamSpec("link.give_up_s", float, 0.0,
              "wall s without a controller (while a task waits) before the node exits 1; "
              "0 = never", min=0.0),
    ParamSpec("link.configure_timeout_s", float, 10.0,
              "wall s configure tries to connect and check HELLO (with the backoff) before "
              "it fails and the node stays unconfigured", min=0.01, max=3600.0),
)

#: ``safety:``: the link's safety rules (docs/nachi.md, "Safety of the link").
SAFETY_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("safety.f_prewarn_n", float, 20.0,
              "prewarning on |F_RX| or |F_RZ|, N (section 4.2): STOP within the same sample",
              min=0.1),
    ParamSpec("safety.stall_timeout_s", float, 0.3,
              "wall s without a sample during a task before STOP", min=0.01),
    ParamSpec("safety.bad_line_limit", int, 3,
              "consecutive malformed / oversize / non-finite lines that stop a task", min=1),
    ParamSpec("safety.stop_timeout_s", float, 2.0,
              "wall s for DONE after STOP before the link is closed", min=0.01),
    *speed_limit_specs("safety", "forwarded as V"),
    *slowdown_specs("safety"),  # Eq. M6, as peel_sim_node's (peel_bridge.slowdown)
)

#: ``node:``: the task sequence, as peel_sim_node's (:data:`peel_bridge.parameters.LOOP_SPECS`).
NODE_SPECS: tuple[ParamSpec, ...] = (*LOOP_SPECS, AUTOSTART)

#: The groups of the bridge's own parameters.
GROUPS = ("link", "safety", "node")

#: Everything the node declares.
SPECS: tuple[ParamSpec, ...] = (*LINK_SPECS, *SAFETY_SPECS, *NODE_SPECS, USE_SIM_TIME)
