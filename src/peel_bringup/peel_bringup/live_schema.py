"""The channels of the live view (``peel graph --live``, :mod:`.live_node`) as plain data: their
JSON schemas and the conversion of what the graph publishes into their messages. Imports no ROS
and no Foxglove: messages are read by attribute (duck-typed), so a test builds them from
anything.

Two kinds of channel, every one JSON-encoded with a JSON schema (docs/graph.md, "Live view"):

* **ROS-shaped** (:data:`ROS_SHAPED`): ``/peel/wrench``, ``/peel/twist``, ``/peel/pose``,
  ``/peel/cmd_vel``, ``/peel/model_version``, ``/diagnostics`` keep their topic names, field
  names and SI units (``wrench.force.x`` = F_RX in N, ``twist.linear.x`` in m/s, ...), and the
  schema is titled with the ROS type, so one Foxglove layout reads them live and from a bag.
* **Decoded** (:data:`DECODED`): what travels as JSON text or a packed array on the wire,
  typed: the model in use and its identity (``/peel/model_info``), the learner's update reports
  (``/peel/model_update``), each finished task (``/peel/trajectory``) with the paper's J split
  into its terms (Eq. 3-5), the planner's margins and latency and each plant bridge's link state
  (both from ``/diagnostics``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from peel_msgs_py import topics, units
from peel_msgs_py.diagnostics import LEVEL_NAMES

JsonSchema = dict[str, Any]
Message = dict[str, Any]

LIVE_MODEL = "/peel/live/model"
LIVE_UPDATE = "/peel/live/model_update"
LIVE_TASK = "/peel/live/task"
LIVE_PLANNER = "/peel/live/planner"
LIVE_LINK = "/peel/live/link"

NUMBER: JsonSchema = {"type": "number"}
INTEGER: JsonSchema = {"type": "integer"}
STRING: JsonSchema = {"type": "string"}
NUMBER_OR_NULL: JsonSchema = {"type": ["number", "null"]}
INTEGER_OR_NULL: JsonSchema = {"type": ["integer", "null"]}
STRING_OR_NULL: JsonSchema = {"type": ["string", "null"]}


def obj(properties: Mapping[str, JsonSchema], title: str | None = None,
        description: str | None = None) -> JsonSchema:
    """An object schema whose every property is required."""
    out: JsonSchema = {"type": "object", "properties": dict(properties),
                       "required": list(properties)}
    if title:
        out = {"title": title, **out}
    if description:
        out["description"] = description
    return out


def array(items: JsonSchema) -> JsonSchema:
    return {"type": "array", "items": items}


# ------------------------------------------------------------------ ROS-shaped channels
TIME = obj({"sec": INTEGER, "nanosec": INTEGER})
HEADER = obj({"stamp": TIME, "frame_id": STRING})
VECTOR3 = obj({"x": NUMBER, "y": NUMBER, "z": NUMBER})
QUATERNION = obj({"x": NUMBER, "y": NUMBER, "z": NUMBER, "w": NUMBER})
TWIST_STAMPED = obj({"header": HEADER, "twist": obj({"linear": VECTOR3, "angular": VECTOR3})},
                    "geometry_msgs/msg/TwistStamped", "SI: m/s, rad/s")

#: topic -> JSON schema of the channels that keep the ROS message's shape.
ROS_SHAPED: dict[str, JsonSchema] = {
    topics.WRENCH: obj({"header": HEADER, "wrench": obj({"force": VECTOR3, "torque": VECTOR3})},
                       "geometry_msgs/msg/WrenchStamped", "force.x = F_RX, force.z = F_RZ, N"),
    topics.TWIST: TWIST_STAMPED,
    topics.POSE: obj({"header": HEADER,
                      "pose": obj({"position": VECTOR3, "orientation": QUATERNION})},
                     "geometry_msgs/msg/PoseStamped", "position.x = q, m"),
    topics.CMD_VEL: TWIST_STAMPED,
    topics.MODEL_VERSION: obj({"data": INTEGER}, "std_msgs/msg/Int64"),
    topics.DIAGNOSTICS: obj({"header": HEADER, "status": array(obj({
        "level": INTEGER, "name": STRING, "message": STRING, "hardware_id": STRING,
        "values": array(obj({"key": STRING, "value": STRING}))}))},
        "diagnostic_msgs/msg/DiagnosticArray"),
}


def ros_time(stamp: Any) -> Message:
    return {"sec": int(stamp.sec), "nanosec": int(stamp.nanosec)}


def stamp_ns(msg: Any) -> int:
    """``header.stamp`` in ns (the ROS time of the sample: simulated time under use_sim_time)."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def header(h: Any) -> Message:
    return {"stamp": ros_time(h.stamp), "frame_id": str(h.frame_id)}


def vector3(v: Any) -> Message:
    return {"x": float(v.x), "y": float(v.y), "z": float(v.z)}


def wrench_stamped(msg: Any) -> Message:
    return {"header": header(msg.header), "wrench": {"force": vector3(msg.wrench.force),
                                                     "torque": vector3(msg.wrench.torque)}}


def twist_stamped(msg: Any) -> Message:
    return {"header": header(msg.header), "twist": {"linear": vector3(msg.twist.linear),
                                                    "angular": vector3(msg.twist.angular)}}


def pose_stamped(msg: Any) -> Message:
    o = msg.pose.orientation
    return {"header": header(msg.header),
            "pose": {"position": vector3(msg.pose.position),
                     "orientation": {"x": float(o.x), "y": float(o.y), "z": float(o.z),
                                     "w": float(o.w)}}}


def int64(msg: Any) -> Message:
    return {"data": int(msg.data)}


def level_of(status: Any) -> int:
    """A ``DiagnosticStatus.level`` as an int (rclpy gives the ``byte`` field as bytes)."""
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def diagnostic_array(msg: Any) -> Message:
    return {"header": header(msg.header), "status": [
        {"level": level_of(s), "name": str(s.name), "message": str(s.message),
         "hardware_id": str(s.hardware_id),
         "values": [{"key": str(kv.key), "value": str(kv.value)} for kv in s.values]}
        for s in msg.status]}


# ------------------------------------------------------------------ decoded channels
MODEL = obj({"version": INTEGER, "sha256": STRING, "path": STRING, "producer": STRING_OR_NULL,
             "task": INTEGER_OR_NULL}, "peel.live.Model",
            "the model the planner plans with (/peel/model_info, decoded)")
UPDATE = obj({"producer": STRING, "task": INTEGER, "status": STRING, "reason": STRING,
              "sha256": STRING_OR_NULL, "path": STRING_OR_NULL, "version": INTEGER_OR_NULL,
              "cell": STRING_OR_NULL}, "peel.live.ModelUpdate",
             "the learner's update after a task (/peel/model_update)")
#: Per-sample columns of a task report, SI (the trajectory codec's wire units).
SAMPLE_COLUMNS = {"t_s": ("t", None), "q_m": ("q", units.mm_to_m),
                  "v_mps": ("v", units.mmps_to_mps), "u_mps": ("u", units.mmps_to_mps),
                  "fx_n": ("fx", None), "fz_n": ("fz", None)}
#: The paper's critics of J (Eq. 3): Eq. 4's progress and force terms, Eq. 5's phi.
J_TERMS = ("progress", "force_x", "force_z", "terminal")
TASK = obj({
    "task": INTEGER, "outcome": STRING, "samples": INTEGER, "t_cpl_s": NUMBER,
    "sum_fx_n": NUMBER, "sum_fz_n": NUMBER, "peak_fx_n": NUMBER, "peak_fz_n": NUMBER,
    "model_version": INTEGER_OR_NULL,
    "cost": obj({"J": NUMBER, **{name: NUMBER for name in J_TERMS}, "reached": {"type": "boolean"}},
                description="J of Eq. 3 and its terms: Eq. 4 progress, force_x, force_z; "
                            "Eq. 5 terminal phi"),
    "series": obj({name: array(NUMBER) for name in SAMPLE_COLUMNS},
                  description="per sample, SI: t s, q m, v and u m/s, F_RX and F_RZ N"),
}, "peel.live.Task", "a finished task (/peel/trajectory, decoded), with J split into its terms")
#: key value of the planner's /diagnostics status (peel_planner_node.health) -> field.
PLANNER_KEYS = {
    "model version": "model_version", "plans": "plans",
    "plan latency median (ms)": "plan_latency_median_ms",
    "plan latency max (ms)": "plan_latency_max_ms", "control period (ms)": "control_period_ms",
    "late commands": "late_commands", "prewarning (N)": "prewarning_n",
    "barrier onset (N)": "barrier_onset_n", "planning margin (N)": "planning_margin_n",
    "task margin (N)": "task_margin_n", "model-error margin (N)": "model_error_margin_n",
}
#: Fields of :data:`PLANNER_KEYS` that count (integers).
PLANNER_COUNTS = ("model_version", "plans", "late_commands")
#: Prefix of the planner's key values holding the last plan's cost per term
#: (``peel_planner_node.health.PLAN_COST``).
PLAN_COST = "plan cost "
#: The planner's default critics (``peel_planner_node.cost.default_critics``) and Eq. 38's
#: control term: the last plan's omega-weighted cost of each (null before the first plan).
PLAN_TERMS = ("progress", "force_x", "force_z", "terminal", "barrier", "cost_to_go", "control")
PLANNER = obj({"level": INTEGER, "level_name": STRING, "message": STRING,
               **{field: INTEGER_OR_NULL if field in PLANNER_COUNTS else NUMBER_OR_NULL
                  for field in PLANNER_KEYS.values()},
               "plan_costs": obj({name: NUMBER_OR_NULL for name in PLAN_TERMS},
                                 description="the last plan's cost per term: Eq. 4 progress, "
                                             "force_x, force_z; Eq. 5 terminal; barrier, "
                                             "cost_to_go (planning only); Eq. 38 control")},
              "peel.live.Planner",
              "the planner's latency, force margins and per-term plan costs (/diagnostics)")
LINK = obj({"cell": STRING, "hardware_id": STRING, "level": INTEGER, "level_name": STRING,
            "message": STRING, "link_state": STRING},
           "peel.live.Link", "a plant bridge's link state (/diagnostics)")

#: topic -> JSON schema of the decoded channels.
DECODED: dict[str, JsonSchema] = {LIVE_MODEL: MODEL, LIVE_UPDATE: UPDATE, LIVE_TASK: TASK,
                                  LIVE_PLANNER: PLANNER, LIVE_LINK: LINK}
#: Every channel of the live view.
CHANNELS: dict[str, JsonSchema] = {**ROS_SHAPED, **DECODED}


def model_record(rec: Any) -> Message:
    """A :class:`~peel_msgs_py.modelinfo.ModelRecord` as a message."""
    return {"version": int(rec.version), "sha256": rec.sha256, "path": rec.path,
            "producer": rec.producer, "task": rec.task}


def update_report(rep: Any) -> Message:
    """A :class:`~peel_msgs_py.modelinfo.UpdateReport` as a message."""
    return {"producer": rep.producer, "task": int(rep.task), "status": rep.status,
            "reason": rep.reason, "sha256": rep.sha256, "path": rep.path,
            "version": rep.version, "cell": rep.cell}


def _peak(values: Sequence[float]) -> float:
    return max((abs(float(v)) for v in values), default=0.0)


def task_report(task: int, traj: Any, terms: Mapping[str, Any]) -> Message:
    """A finished trajectory (paper units, :class:`~peel_msgs_py.trajectory.Trajectory`) and
    ``terms``, J of Eq. 3 split into the paper's critics
    (:func:`peel_planner_node.cost.episode_cost_terms`), as a message in SI units."""
    version = traj.meta.get("model_version")
    series = {}
    for name, (attr, convert) in SAMPLE_COLUMNS.items():
        col = getattr(traj, attr)
        series[name] = [float(convert(x) if convert else x) for x in col]
    return {
        "task": int(task), "outcome": traj.outcome, "samples": len(traj),
        "t_cpl_s": float(traj.t_cpl), "sum_fx_n": float(traj.sum_fx),
        "sum_fz_n": float(traj.sum_fz), "peak_fx_n": _peak(traj.fx), "peak_fz_n": _peak(traj.fz),
        "model_version": None if version is None else int(version),
        "cost": {"J": float(terms["total"]), **{name: float(terms[name]) for name in J_TERMS},
                 "reached": bool(terms["reached"])},
        "series": series,
    }


def number(text: str) -> float | None:
    """A key value back as a number (:func:`peel_msgs_py.diagnostics.text`); None for ``-``,
    for text that is not a number, and for a non-finite one (JSON has none)."""
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _status_head(status: Message) -> Message:
    level = int(status["level"])
    return {"level": level, "level_name": LEVEL_NAMES.get(level, str(level)),
            "message": status["message"]}


def planner_state(status: Message) -> Message | None:
    """The planner's status of a ``/diagnostics`` message (:func:`diagnostic_array`) as a
    message; None for any other status (it has no ``planning margin (N)``)."""
    values = {kv["key"]: kv["value"] for kv in status["values"]}
    if "planning margin (N)" not in values:
        return None
    out = {field: number(values.get(key, "-")) for key, field in PLANNER_KEYS.items()}
    for field in PLANNER_COUNTS:
        out[field] = None if out[field] is None else int(out[field])
    costs = {name: number(values.get(PLAN_COST + name, "-")) for name in PLAN_TERMS}
    return {**_status_head(status), **out, "plan_costs": costs}


def link_state(status: Message) -> Message | None:
    """A plant bridge's status as a message: the Nachi bridge's ``link state``; the simulator
    bridge, whose plant runs in its own process, reports its phase; None for other nodes."""
    values = {kv["key"]: kv["value"] for kv in status["values"]}
    if "link state" in values:
        state = values["link state"]
    elif "phase" in values:
        state = f"simulated ({values['phase']})"
    else:
        return None
    return {"cell": status["name"], "hardware_id": status["hardware_id"],
            **_status_head(status), "link_state": state}
