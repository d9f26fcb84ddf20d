"""The topic table of peel: names, ROS types, rates, QoS profiles and contents, as plain data.

Everything on the wire is SI (REP-103): positions in m, velocities in m/s, forces in N, time in s.
The algorithms work in the paper's units (mm, mm/s); the conversion happens only in
:mod:`peel_msgs_py.units`, called from node code, :mod:`peel_msgs_py.codec` and the bag readers.

QoS profiles are plain, hashable :class:`~peel_msgs_py.qos.QosSpec` values (:mod:`peel_msgs_py.qos`)
so that this module imports no ROS; :func:`qos_profile` turns one into rclpy's ``QoSProfile``
(:mod:`peel_msgs_py.ros.qos`) and :meth:`~peel_msgs_py.qos.QosSpec.to_bag` into the
``offered_qos_profiles`` entry rosbag2 writes.

Choices (docs/interfaces.md gives the reasons at length):

* streams (wrench, twist, pose, cmd_vel) are RELIABLE, KEEP_LAST 10, VOLATILE: on one machine
  reliability costs nothing, the recorder and the trajectory must not lose samples, and a
  reliable publisher still matches best-effort subscribers (``SensorDataQoS`` tools);
* ``/peel/trajectory`` is RELIABLE, KEEP_LAST 10: one message per task, each must reach the
  learner and the recorder;
* latched state (``/peel/model_version``) is RELIABLE, KEEP_LAST 1, TRANSIENT_LOCAL so a late
  joiner (and the recorder) gets the current value, as ``/tf_static`` does;
* the planner's model records (``/peel/model_info``, one per swap) are RELIABLE, KEEP_LAST 16,
  TRANSIENT_LOCAL: every record must reach the launcher, the bridge and the learner, which wait
  for the record of an update before they go on, and a reader that discovery matched late
  still gets the last 16 in order, the current one last;
* ``/peel/model_update`` (one report per task from the learner) is RELIABLE, KEEP_LAST 10,
  TRANSIENT_LOCAL: a reader matched late (Fast DDS took up to 3 s to match a new process here,
  longer than a short run) still gets the last 10 reports instead of waiting for one forever;
* ``/clock`` is published RELIABLE, KEEP_LAST 1 (matches every subscriber) and subscribed
  BEST_EFFORT, KEEP_LAST 1, as rclpy's time source does (matches every publisher);
* ``/diagnostics`` (every node's health, :mod:`peel_msgs_py.diagnostics`) is RELIABLE, KEEP_LAST
  10, VOLATILE like the streams; it is ROS's standard topic, not a peel one, and not recorded by
  default (:data:`STATUS_TOPICS`, beside :data:`TOPICS`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from .errors import PeelError
from .qos import (
    CLOCK_QOS,
    CLOCK_SUB_QOS,
    LATCHED_QOS,
    RECORD_QOS,
    REPORT_QOS,
    STREAM_QOS,
    TRAJECTORY_QOS,
    QosSpec,
)


# ---------------------------------------------------------------------------------- topic table
@dataclass(frozen=True)
class TopicSpec:
    """One row of the topic table."""

    name: str
    type: str  # ROS type name, pkg/msg/Type
    rate_hz: float | None  # nominal rate; None = event driven
    qos: QosSpec  # profile publishers offer
    publisher: str  # node that publishes it
    content: str  # fields used and their meaning
    units: str

    @property
    def sub_qos(self) -> QosSpec:
        """Profile a subscriber (the recorder) uses: the offered one, best effort for /clock.

        The latched ``/peel/model_version`` is read with a deeper history (transient local,
        depth 16) so that two swaps in quick succession both reach a subscriber matched in
        time (and the bag), while a late joiner receives only the current value that the
        publisher keeps; ``/peel/model_info``'s publisher keeps its last 16 records itself.
        """
        if self.name == CLOCK:
            return CLOCK_SUB_QOS
        if self.qos == LATCHED_QOS:
            return replace(self.qos, depth=16)
        return self.qos

    @property
    def rate_text(self) -> str:
        return f"{self.rate_hz:g} Hz" if self.rate_hz else "event"


WRENCH = "/peel/wrench"
TWIST = "/peel/twist"
POSE = "/peel/pose"
CMD_VEL = "/peel/cmd_vel"
TRAJECTORY = "/peel/trajectory"
MODEL_VERSION = "/peel/model_version"
MODEL_INFO = "/peel/model_info"
MODEL_UPDATE = "/peel/model_update"
PLANNER_SAFETY = "/peel/planner_safety"
CLOCK = "/clock"
DIAGNOSTICS = "/diagnostics"

#: Prefix of ``header.frame_id`` of every stamped message: the frame of task k is
#: ``peel_task_<k>`` (see :func:`peel_msgs_py.codec.task_frame_id`): origin at that task's point C,
#: x along the peel direction, z up (REP-103, right-handed). Each task peels a new panel, so each
#: has its own origin C, and the frame id tells subscribers which task a sample belongs to.
FRAME_PREFIX = "peel_task_"

#: Sample rate of the state streams (dt = 0.1 s) and of the planner (control period 0.5 s).
STATE_RATE_HZ = 10.0
CONTROL_RATE_HZ = 2.0

_TABLE: tuple[TopicSpec, ...] = (
    TopicSpec(
        WRENCH, "geometry_msgs/msg/WrenchStamped", STATE_RATE_HZ, STREAM_QOS, "peel_sim_node",
        "contact force on the blade: wrench.force.x = F_RX (horizontal, peel direction), "
        "wrench.force.z = F_RZ (vertical); torque unused (0)", "N",
    ),
    TopicSpec(
        TWIST, "geometry_msgs/msg/TwistStamped", STATE_RATE_HZ, STREAM_QOS, "peel_sim_node",
        "measured blade velocity along the peel axis, twist.linear.x = v_k "
        "(= (q_k - q_{k-1}) / dt); other components 0", "m/s",
    ),
    TopicSpec(
        POSE, "geometry_msgs/msg/PoseStamped", STATE_RATE_HZ, STREAM_QOS, "peel_sim_node",
        "blade position along the peel axis from point C, pose.position.x = q_k; "
        "orientation identity; header.frame_id = peel_task_<k> marks the task", "m",
    ),
    TopicSpec(
        CMD_VEL, "geometry_msgs/msg/TwistStamped", CONTROL_RATE_HZ, STREAM_QOS,
        "peel_planner_node",
        "planner command u*, twist.linear.x, held over the next control period (0.5 s)",
        "m/s",
    ),
    TopicSpec(
        TRAJECTORY, "std_msgs/msg/Float64MultiArray", None, TRAJECTORY_QOS, "peel_sim_node",
        "the finished task: t, q, v, u, F_RX, F_RZ, psi per sample, outcome, parameters and "
        "provenance (layout in peel_msgs_py.codec)", "s, m, m/s, N",
    ),
    TopicSpec(
        MODEL_VERSION, "std_msgs/msg/Int64", None, LATCHED_QOS, "peel_planner_node",
        "version of the forward model the planner uses: 0 = its starting model, +1 on every "
        "accepted model swap, never taken from a file name (identity: /peel/model_info)", "-",
    ),
    TopicSpec(
        MODEL_INFO, "std_msgs/msg/String", None, RECORD_QOS, "peel_planner_node",
        "the model behind each version, JSON: version, sha256 (of its safetensors), path, "
        "producer and task (the learner's update after task k; null for any other model); "
        "published with every /peel/model_version (layout in peel_msgs_py.modelinfo)", "-",
    ),
    TopicSpec(
        MODEL_UPDATE, "std_msgs/msg/String", None, REPORT_QOS, "model_learner_node",
        "what became of the learner's update after each task, JSON: producer, task, status "
        "(swapped / refused / failed / skipped), reason, sha256, path "
        "(peel_msgs_py.modelinfo)", "-",
    ),
    TopicSpec(
        PLANNER_SAFETY, "std_msgs/msg/String", CONTROL_RATE_HZ, STREAM_QOS,
        "peel_planner_node",
        "the guard of the force limit after each plan, JSON: task and the task's counts "
        "(plans, commands_reduced, fallbacks, all_samples_unsafe, commands_slowed, margin_from_horizon, "
        "margin_*_n per axis); the plant bridges put the last one of each task into its trajectory's meta",
        "N, mm/s",
    ),
    TopicSpec(
        CLOCK, "rosgraph_msgs/msg/Clock", STATE_RATE_HZ, CLOCK_QOS, "peel_sim_node",
        "simulated time, when use_sim_time is set (one tick per sample)", "s",
    ),
)

#: Every node's health (peel_msgs_py.diagnostics), ROS's standard topic: not recorded by default.
_STATUS_TABLE: tuple[TopicSpec, ...] = (
    TopicSpec(
        DIAGNOSTICS, "diagnostic_msgs/msg/DiagnosticArray", 1.0, STREAM_QOS, "every peel node",
        "one DiagnosticStatus per node part, level OK / WARN / ERROR, the reason as message, "
        "key values (link state and fault counts, plan() latency against the control period, "
        "model version, update time and result; docs/interfaces.md); 1 Hz of wall time",
        "names carry them (s, ms, N)",
    ),
)

#: name -> spec, in table order: the peel topics and /clock.
TOPICS: dict[str, TopicSpec] = {spec.name: spec for spec in _TABLE}
#: name -> spec of the topics beside them (``/diagnostics``).
STATUS_TOPICS: dict[str, TopicSpec] = {spec.name: spec for spec in _STATUS_TABLE}

#: What ``peel record`` records by default: every /peel topic and /clock.
RECORDED_TOPICS: tuple[str, ...] = tuple(TOPICS)


def namespace_remaps() -> list[str]:
    """ROS arguments that make every topic of the table relative to the node's namespace.

    ``-r /peel/wrench:=peel/wrench`` (and so on for each topic of :data:`TOPICS`, ``/clock``
    included, and rclpy's own ``/clock`` subscription of ``use_sim_time`` with it): a name
    whose replacement is relative is resolved against the node's namespace, so under the root
    namespace every name stays exactly as in the table, and ``-r __ns:=/cell_a`` moves the
    whole cell to ``/cell_a/peel/wrench``, ``/cell_a/clock``, ... . ``/diagnostics`` stays
    global (ROS's standard topic; every status names its node, namespace included). Every
    peel node's ``main`` appends these after the user's own rules, which therefore win.
    """
    args = ["--ros-args"]
    for name in TOPICS:
        args += ["-r", f"{name}:={name.lstrip('/')}"]
    return args


def under(namespace: str, name: str) -> str:
    """The absolute name of table topic ``name`` in a node of ``namespace`` (``""`` or ``"/"``
    = the root: the table's name itself): ``under("/cell_a", WRENCH) == "/cell_a/peel/wrench"``."""
    ns = namespace.rstrip("/")
    return f"{ns}{name}" if ns else name


def topic(name: str) -> TopicSpec:
    """The spec of a topic of the table; :class:`PeelError` naming it when unknown."""
    try:
        return TOPICS[name] if name in TOPICS else STATUS_TOPICS[name]
    except KeyError:
        raise PeelError(
            f"unknown topic {name!r} (known: {', '.join([*TOPICS, *STATUS_TOPICS])})"
        ) from None


def qos_profile(spec: QosSpec | TopicSpec | str, *, subscriber: bool = False) -> Any:
    """rclpy's ``QoSProfile`` for a spec, a topic spec or a topic name.

    ``subscriber=True`` gives the profile a subscriber should use (:attr:`TopicSpec.sub_qos`).
    Imports rclpy (through :mod:`peel_msgs_py.ros.qos`) on call.
    """
    if isinstance(spec, str):
        spec = topic(spec)
    if isinstance(spec, TopicSpec):
        spec = spec.sub_qos if subscriber else spec.qos
    from .ros.qos import to_profile

    return to_profile(spec)


def markdown_table() -> str:
    """The topic table as Markdown (docs/interfaces.md and the README embed it)."""
    rows = [
        "| topic | type | rate | QoS | publisher | content | units |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in (*_TABLE, *_STATUS_TABLE):
        rows.append(
            f"| `{s.name}` | {s.type} | {s.rate_text} | {s.qos.describe()} | {s.publisher} "
            f"| {s.content} | {s.units} |"
        )
    return "\n".join(rows)
