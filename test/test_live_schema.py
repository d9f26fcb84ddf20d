"""The live view's channels (:mod:`peel_bringup.live_schema`) and its Foxglove layout.

Every conversion runs on real rclpy messages or on the statuses the nodes' own health functions
build, and its output is checked against its channel's JSON schema (:func:`conforms`, the
subset of JSON Schema the channels use) and against the values put in. The ROS-shaped channels
must have the ROS messages' field tree, so that one layout reads the live view and a bag; the
shipped layout may name only channels and fields that exist, and draws the prewarning the
planner is configured with. Without ``--live`` nothing imports the Foxglove SDK.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from std_msgs.msg import Int64

from peel_bag.recorder_node import message_class
from peel_bringup import live_schema as S
from peel_msgs_py import topics
from peel_msgs_py.diagnostics import DurationWindow, Status
from peel_msgs_py.errors import PeelError
from peel_msgs_py.modelinfo import ModelRecord, UpdateReport
from peel_msgs_py.params import load_node_params
from peel_msgs_py.ros.diagnostics import status_msg
from peel_msgs_py.trajectory import Trajectory

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "config" / "foxglove" / "peel_layout.json"
TYPES = {"number": (int, float), "integer": (int,), "string": (str,), "boolean": (bool,),
         "null": (type(None),), "object": (dict,), "array": (list,)}


def conforms(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    """Assert ``value`` is valid under ``schema`` (type, properties, required, items)."""
    kinds = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
    ok = any(isinstance(value, TYPES[k]) and not (k in ("number", "integer") and
                                                  isinstance(value, bool)) for k in kinds)
    assert ok, f"{where}: {value!r} is not {kinds}"
    if isinstance(value, float):
        assert np.isfinite(value), f"{where}: non-finite"
    if isinstance(value, dict):
        assert set(value) == set(schema["properties"]) == set(schema["required"]), where
        for key, sub in schema["properties"].items():
            conforms(value[key], sub, f"{where}.{key}")
    if isinstance(value, list):
        for i, item in enumerate(value):
            conforms(item, schema["items"], f"{where}[{i}]")


def stamped(msg: Any, sec: int = 12, nanosec: int = 300_000_000, frame: str = "peel_task_2"
            ) -> Any:
    msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = sec, nanosec, frame
    return msg


def test_ros_shaped_messages_keep_their_fields_and_si_values() -> None:
    w = stamped(WrenchStamped())
    w.wrench.force.x, w.wrench.force.z = 13.25, -4.5
    t = stamped(TwistStamped())
    t.twist.linear.x = 0.0035
    p = stamped(PoseStamped())
    p.pose.position.x, p.pose.orientation.w = 0.0061, 1.0
    cases = {topics.WRENCH: S.wrench_stamped(w), topics.TWIST: S.twist_stamped(t),
             topics.POSE: S.pose_stamped(p), topics.CMD_VEL: S.twist_stamped(t),
             topics.MODEL_VERSION: S.int64(Int64(data=3))}
    for name, message in cases.items():
        conforms(message, S.CHANNELS[name], name)
    assert cases[topics.WRENCH]["wrench"]["force"] == {"x": 13.25, "y": 0.0, "z": -4.5}
    assert cases[topics.WRENCH]["header"] == {"stamp": {"sec": 12, "nanosec": 300_000_000},
                                              "frame_id": "peel_task_2"}
    assert cases[topics.TWIST]["twist"]["linear"]["x"] == 0.0035
    assert cases[topics.POSE]["pose"]["position"]["x"] == 0.0061
    assert cases[topics.POSE]["pose"]["orientation"]["w"] == 1.0
    assert cases[topics.MODEL_VERSION] == {"data": 3}
    assert S.stamp_ns(w) == 12_300_000_000


def ros_fields(type_name: str) -> dict[str, Any]:
    """The field tree of a ROS message type: name -> subtree (None for a plain value)."""
    cls = message_class(type_name)
    out: dict[str, Any] = {}
    for name, kind in cls.get_fields_and_field_types().items():
        base = kind.removeprefix("sequence<").removesuffix(">")
        out[name] = ros_fields(base.replace("/", "/msg/", 1)) if "/" in base else None
    return out


def schema_fields(schema: dict[str, Any]) -> dict[str, Any] | None:
    if schema["type"] == "array":
        return schema_fields(schema["items"])
    if schema["type"] != "object":
        return None
    return {name: schema_fields(sub) for name, sub in schema["properties"].items()}


@pytest.mark.parametrize("name", sorted(S.ROS_SHAPED))
def test_ros_shaped_channels_have_the_ros_field_tree(name: str) -> None:
    """Titled with the topic's ROS type and with its fields: the layout's paths read the live
    channel and the bag alike."""
    schema = S.ROS_SHAPED[name]
    assert schema["title"] == topics.topic(name).type
    assert schema_fields(schema) == ros_fields(schema["title"])


def diagnostics(*statuses: Status) -> dict[str, Any]:
    msg = stamped(DiagnosticArray(status=[status_msg(s) for s in statuses]), frame="")
    out = S.diagnostic_array(msg)
    conforms(out, S.CHANNELS[topics.DIAGNOSTICS])
    return out


def test_planner_status_becomes_typed_margins_and_latency() -> None:
    """From the planner's own report (peel_planner_node.health): numbers back from the text of
    the key values, counts as integers, '-' as null."""
    from peel_planner_node.config import PlannerConfig
    from peel_planner_node.health import planner_status

    cfg = PlannerConfig.from_params(load_node_params("peel_planner_node"))
    latency = DurationWindow(budget_s=0.5)
    for s in (0.010, 0.020, 0.600):
        latency.add(s)
    model = ModelRecord(version=4, sha256="ab" * 32, path="/m/model_v0004.safetensors",
                        producer="/model_learner_node", task=3)
    status = planner_status(latency, cfg, model, None, 0, peak_n=12.5, error_margin_n=1.25)
    (raw,) = diagnostics(status)["status"]
    state = S.planner_state(raw)
    assert state is not None
    conforms(state, S.CHANNELS[S.LIVE_PLANNER])
    prewarn = cfg.safety.f_prewarn_n
    assert state["level"] == 1 and state["level_name"] == "WARN"  # one plan over the period
    assert state["model_version"] == 4 and state["plans"] == 3 and state["late_commands"] == 1
    assert state["plan_latency_median_ms"] == pytest.approx(20.0)
    assert state["plan_latency_max_ms"] == pytest.approx(600.0)
    assert state["control_period_ms"] == pytest.approx(500.0)
    assert state["prewarning_n"] == prewarn
    assert state["planning_margin_n"] == pytest.approx(prewarn - cfg.cost.barrier.start_n)
    assert state["task_margin_n"] == pytest.approx(prewarn - 12.5)
    assert state["model_error_margin_n"] == pytest.approx(1.25)
    idle = planner_status(DurationWindow(budget_s=0.5), cfg, model, None, 0, peak_n=None)
    idle_state = S.planner_state(diagnostics(idle)["status"][0])
    assert idle_state is not None and idle_state["task_margin_n"] is None
    assert idle_state["plan_latency_median_ms"] is None
    assert set(idle_state["plan_costs"].values()) == {None}  # no plan yet
    assert S.link_state(raw) is None


def test_plan_costs_are_the_omega_weighted_terms_of_the_last_plan() -> None:
    """One plan of the real planner (its default critics): each term's cost is omega (Eq. 38)
    times that critic's costs of the samples, and together with the control term they are
    omega times the samples' whole cost; the live channel carries them as numbers."""
    import torch

    from peel_planner_node.config import PlannerConfig
    from peel_planner_node.cost import Cost
    from peel_planner_node.health import plan_costs, planner_status
    from peel_planner_node.mppi import Planner

    class Linear:
        def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
            q = float(history.q[-1]) + 0.1 * torch.cumsum(v, dim=1)
            return torch.stack([q, 1.5 * v + 8.0, torch.full_like(v, 3.0)], dim=-1)

    cfg = PlannerConfig.from_params(load_node_params("peel_planner_node")).replace(
        **{"mppi.n_samples": 9, "mppi.horizon": 3, "mppi.dtype": "float64"})
    planner = Planner(Linear(), Cost(cfg.cost), cfg)
    assert plan_costs(planner.last) == {}
    hist = Trajectory(t=np.arange(6) * 0.1, q=np.arange(6) * 0.2, v=np.full(6, 2.0),
                      u=np.full(6, 2.0), fx=np.full(6, 11.0), fz=np.full(6, 3.0),
                      psi=np.full(6, np.nan))
    planner.update(hist)
    last = planner.last
    costs = plan_costs(last)
    assert set(costs) == set(S.PLAN_TERMS)
    omega = last["omega"]
    for name, v in last["terms"].items():
        assert costs[name] == pytest.approx(float(omega @ v))
    assert sum(costs.values()) == pytest.approx(float(omega @ (last["cost"] + last["control"])))
    model = ModelRecord(version=0, sha256="ab" * 32, path="/m/init.safetensors")
    status = planner_status(DurationWindow(budget_s=0.5), cfg, model, None, 0, None, 0.0, costs)
    state = S.planner_state(diagnostics(status)["status"][0])
    assert state is not None
    conforms(state, S.CHANNELS[S.LIVE_PLANNER])
    for name in S.PLAN_TERMS:  # the key values' 6 significant digits
        assert state["plan_costs"][name] == pytest.approx(costs[name], rel=1e-5, abs=1e-9)


def test_bridge_statuses_become_link_states() -> None:
    from peel_sim_node.health import sim_status

    sim = sim_status("sim", "task", 1, 3, 0, None, 5.0, None)
    nachi = Status("peel_nachi_bridge: controller link", 2, "no link to the controller",
                   "127.0.0.1:5100", (("link state", "disconnected"), ("reconnects", "2")))
    planner_less = Status("model_learner_node: online learning", 0, "ok", "learner")
    statuses = diagnostics(sim, nachi, planner_less)["status"]
    assert statuses[1]["level"] == 2  # the byte field of rclpy, as an integer
    links = [S.link_state(s) for s in statuses]
    for link in links[:2]:
        conforms(link, S.CHANNELS[S.LIVE_LINK])
    assert links[0]["link_state"] == "simulated (task)" and links[0]["level_name"] == "OK"
    assert links[1] == {"cell": "peel_nachi_bridge: controller link",
                        "hardware_id": "127.0.0.1:5100", "level": 2, "level_name": "ERROR",
                        "message": "no link to the controller", "link_state": "disconnected"}
    assert links[2] is None and S.planner_state(statuses[2]) is None


def trajectory() -> Trajectory:
    t = np.arange(12) * 0.1
    q = np.minimum(t * 6.0, 6.0)
    v = np.r_[0.0, np.diff(q) / 0.1]
    return Trajectory(t=t, q=q, v=v, u=np.full(12, 6.0), fx=8.0 + t, fz=-(3.0 + t),
                      psi=np.full(12, np.nan), outcome="done", meta={"model_version": 2})


def test_task_report_is_si_with_the_terms_of_j() -> None:
    from peel_planner_node.config import PlannerConfig
    from peel_planner_node.cost import Cost, episode_cost

    cost = Cost(PlannerConfig.from_params(load_node_params("peel_planner_node")).cost)
    traj = trajectory()
    report = S.task_report(2, traj, cost.episode_terms(traj))
    conforms(report, S.CHANNELS[S.LIVE_TASK])
    assert report["task"] == 2 and report["outcome"] == "done" and report["samples"] == 12
    assert report["model_version"] == 2 and report["t_cpl_s"] == pytest.approx(traj.t_cpl)
    assert report["peak_fx_n"] == pytest.approx(9.1) and report["peak_fz_n"] == pytest.approx(4.1)
    c = report["cost"]
    assert c["J"] == pytest.approx(episode_cost(traj, cost))
    assert c["J"] == pytest.approx(sum(c[name] for name in S.J_TERMS))
    assert c["progress"] < 0 < c["force_x"] and c["reached"] is True
    s = report["series"]
    assert s["q_m"] == pytest.approx(list(traj.q / 1000.0))  # mm on the algorithms' side, m here
    assert s["u_mps"] == pytest.approx([0.006] * 12) and s["fz_n"] == pytest.approx(list(traj.fz))


def test_model_record_and_update_report() -> None:
    rec = ModelRecord(version=1, sha256="cd" * 32, path="/m/v1.safetensors",
                      producer="/model_learner_node", task=1)
    conforms(S.model_record(rec), S.CHANNELS[S.LIVE_MODEL])
    assert S.model_record(ModelRecord.from_json(rec.to_json())) == json.loads(rec.to_json())
    start = ModelRecord(version=0, sha256="ef" * 32, path="/m/init.safetensors")
    conforms(S.model_record(start), S.CHANNELS[S.LIVE_MODEL])
    rep = UpdateReport(producer="/model_learner_node", task=2, status="refused",
                       reason="predicts non-finite forces")
    conforms(S.update_report(rep), S.CHANNELS[S.LIVE_UPDATE])
    assert S.update_report(rep) == json.loads(rep.to_json())


def test_number_of_a_key_value() -> None:
    assert S.number("20") == 20.0 and S.number("-1.5") == -1.5
    assert S.number("-") is None and S.number("nan") is None and S.number("link up") is None


# ------------------------------------------------------------------ the layout
def panels(node: Any) -> Iterator[str]:
    """The panel ids of a layout tree (Foxglove's mosaic: ids at the leaves)."""
    if isinstance(node, str):
        yield node
    else:
        yield from panels(node["first"])
        yield from panels(node["second"])


def field_exists(path: str) -> bool:
    """Whether ``/topic.field.sub`` names a field of a live channel or of a bag's topic."""
    names = sorted((*S.CHANNELS, *topics.TOPICS), key=len, reverse=True)
    name = next((n for n in names if path == n or path.startswith(n + ".")), None)
    if name is None:
        return False
    tree: Any = schema_fields(S.CHANNELS[name]) if name in S.CHANNELS else \
        ros_fields(topics.topic(name).type)
    for part in filter(None, path[len(name):].split(".")):
        if not isinstance(tree, dict) or part not in tree:
            return False
        tree = tree[part]
    return True


def layout_paths(config: dict[str, Any]) -> list[str]:
    out = [p["value"] for p in config.get("paths", ())]
    return out + [config[k] for k in ("topicPath", "topicToRender") if k in config]


def test_layout_shows_every_channel_from_fields_that_exist() -> None:
    doc = json.loads(LAYOUT.read_text())
    configs = doc["configById"]
    leaves = list(panels(doc["layout"]))
    for cfg in configs.values():  # a tab panel holds layouts of its own
        for tab in cfg.get("tabs", ()):
            leaves += panels(tab["layout"])
    assert sorted(leaves) == sorted(configs)  # every panel placed once, each configured
    paths = [p for cfg in configs.values() for p in layout_paths(cfg)]
    lines = [p for p in paths if S.number(p) is not None]  # Plot reference lines
    for path in set(paths) - set(lines):
        assert field_exists(path), f"the layout names {path}, which no channel has"
    shown = {name for name in S.CHANNELS if any(p == name or p.startswith(name + ".")
                                                for p in paths)}
    assert shown == set(S.CHANNELS)
    force = configs["Plot!force"]["paths"]
    assert {p["value"] for p in force} >= {"/peel/wrench.wrench.force.x",
                                           "/peel/wrench.wrench.force.z"}
    prewarn = load_node_params("peel_planner_node")["safety.f_prewarn_n"]
    assert [float(p) for p in lines if p in {q["value"] for q in force}] == [prewarn]
    # ordered by receive time: live the sample's stamp (the live view's log time), in a bag the
    # recorder's; Foxglove's headerStamp would need {sec, nsec}, not ROS 2's nanosec
    assert {p.get("timestampMethod") for c in configs.values() for p in c.get("paths", ())} \
        == {"receiveTime"}


# ------------------------------------------------------------------ the launcher
def test_graph_without_live_imports_no_foxglove(tmp_path: Path) -> None:
    """Resolving a run without --live (every node's parameters checked) and listing its
    processes imports no Foxglove and starts no live view; with --live on a port in use the
    run is refused before anything starts."""
    code = f"""
import sys
from peel_bringup import demo, graph
run = graph.resolve(graph._parser().parse_args(["--tasks", "1", "--out", {str(tmp_path / 'r')!r}]))
names = [c.name for c in graph.children_of(run)]
assert graph.LIVE not in names, names
assert run.settings()["peel_sim_node"]["node.min_subscribers"] == 1
assert not [m for m in sys.modules if m.split(".")[0] == "foxglove"], "foxglove imported"
print("ok")
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr

    from peel_bringup import graph

    live = graph.resolve(graph._parser().parse_args(
        ["--tasks", "1", "--out", str(tmp_path / "l"), "--live", "18999"]))
    assert live.live == ("127.0.0.1", 18999)
    child = next(c for c in graph.children_of(live) if c.name == graph.LIVE)
    assert child.cmd[1:] == ["-m", "peel_bringup.live_node", "--host", "127.0.0.1",
                             "--port", "18999"]
    assert live.settings()["peel_sim_node"]["node.min_subscribers"] == 2  # planner, live view
    assert live.settings()["peel_planner_node"]["node.min_cmd_subscribers"] == 2
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(PeelError, match=f"--live: cannot serve on 127.0.0.1:{port}"):
            graph.resolve(graph._parser().parse_args(
                ["--tasks", "1", "--out", str(tmp_path / "b"), "--live", str(port)]))
    with pytest.raises(PeelError, match="--live-host needs --live"):
        graph.resolve(graph._parser().parse_args(
            ["--tasks", "1", "--out", str(tmp_path / "h"), "--live-host", "0.0.0.0"]))


def test_demo_passes_live_to_the_graph(tmp_path: Path) -> None:
    from peel_bringup import demo, graph

    for argv, live in (([], None), (["--live"], ("127.0.0.1", graph.LIVE_PORT)),
                       (["--live", "9001", "--live-host", "0.0.0.0"], ("0.0.0.0", 9001))):
        args = demo._parser().parse_args(argv)
        gargs = graph._parser().parse_args(demo.graph_argv(args, tmp_path, tmp_path / "bag"))
        assert (None if gargs.live is None else (gargs.live_host, gargs.live)) == live
