"""The node graph as separate processes on rclpy (docs/graph.md).

Each test starts ``peel graph`` (three node processes + recorder) on a ROS domain of its own
(the ``ros_domain`` fixture of conftest.py; LOCALHOST discovery) with a small parameter override
(short tasks, small N/H, one meta step) and reads the bag back with two independent readers:
``rosbags`` (its rosbag2 reader and Jazzy typestore) and mcap's own ROS 2 decoder
(``mcap-ros2-support``). No node log may hold a traceback (one SIGINT per node at shutdown).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from graph_helpers import ALONE, FAST, SIM_TASKS, Lines, assert_clean_logs, node_env, override_yaml, read_bag_mcap_ros2
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

ROOT = Path(__file__).resolve().parents[1]
SLOT_S = 20.0  # node.task_slot_s in the override: task i starts at ROS time i * SLOT_S


def initial_model(tmp: Path) -> Path:
    """A freshly initialised forward model (seeded): the tests do not depend on training."""
    import torch

    from peel_model.checkpoint import save_checkpoint
    from peel_model.config import ModelConfig
    from peel_model.predictor import ForcePredictor

    torch.manual_seed(0)
    return save_checkpoint(tmp / "init.safetensors", ForcePredictor(ModelConfig()))


def _override(init: Path, wait_model_s: float, meta_steps: int = 1) -> str:
    """Short tasks, small N/H, a small learner update of ``meta_steps`` meta steps."""
    return override_yaml(SIM_TASKS, FAST, ALONE, {
        "peel_sim_node": {"node": {"task_slot_s": SLOT_S, "wait_model_s": wait_model_s}},
        "peel_planner_node": {"model": {"path": init}},
        "model_learner_node": {"node": {"init_model": init}, "maml": {"meta_steps": meta_steps}},
        "peel_bringup": {"graph": {"final_model_wait_s": 120.0}},
    })


def write_override(tmp: Path, wait_model_s: float, meta_steps: int = 1) -> Path:
    path = tmp / "override.yaml"
    path.write_text(_override(initial_model(tmp), wait_model_s, meta_steps))
    return path


def graph_cmd(tmp: Path, *extra: str, tasks: int = 3, wait_model_s: float = 120.0,
              plant: str = "sim", meta_steps: int = 1) -> list[str]:
    return [sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", plant, "--tasks",
            str(tasks), "--params", str(write_override(tmp, wait_model_s, meta_steps)),
            "--out", str(tmp / "run"), "--seed", "3", *extra]


def read_bag(bag: Path) -> dict[str, list[tuple[float, object]]]:
    """topic -> [(header stamp or log time in s, message)] read with rosbags."""
    out: dict[str, list[tuple[float, object]]] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, t_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp if hasattr(msg, "header") else getattr(msg, "clock", None)
            t = stamp.sec + stamp.nanosec * 1e-9 if stamp is not None else t_ns * 1e-9
            out.setdefault(conn.topic, []).append((t, msg))
    return out


def log_times(bag: Path) -> dict[str, list[tuple[int, str]]]:
    """topic -> [(recorder receive time in ns, header frame id or "")] read with rosbags."""
    out: dict[str, list[tuple[int, str]]] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, t_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            frame = msg.header.frame_id if hasattr(msg, "header") else ""
            out.setdefault(conn.topic, []).append((int(t_ns), frame))
    return out


def per_task_steps(stamps: list[float]) -> list[np.ndarray]:
    """Differences of the (unique, sorted) stamps inside each task slot of ROS time."""
    t = np.unique(np.round(np.asarray(stamps), 6))
    slots = np.floor(t / SLOT_S + 1e-9).astype(int)
    return [np.diff(t[slots == s]) for s in np.unique(slots)]


def frame_tasks(msgs: list[tuple[float, object]]) -> set[int]:
    """Task indices named by the header frame ids (peel_task_<k>)."""
    return {int(m.header.frame_id.rsplit("_", 1)[1]) for _, m in msgs}


def test_three_tasks_bag_rates_trajectories_and_model_swaps(tmp_path: Path, ros_domain: str
                                                           ) -> None:
    """On the plant, seed 3; also the same results as ``peel experiment`` (run_job) with the
    same seed, model and parameters."""
    bag = tmp_path / "bag"
    res = subprocess.run(graph_cmd(tmp_path, "--record", str(bag), plant="plant"),
                         env=node_env(), capture_output=True, text=True, timeout=400)
    assert res.returncode == 0, res.stdout + res.stderr
    task_lines = [ln for ln in res.stdout.splitlines() if re.match(r"task \d/3: ", ln)]
    assert len(task_lines) == 3, res.stdout
    assert all(re.search(r"T_cpl=\s*[\d.]+ s\s+J=\s*-?[\d.]+\s.*model v\d+", ln)
               for ln in task_lines), task_lines

    msgs = read_bag(bag)
    # 10 Hz of simulated time: consecutive samples of a task are 0.1 s apart
    for topic in ("/peel/wrench", "/peel/twist", "/peel/pose"):
        steps = per_task_steps([t for t, _ in msgs[topic]])
        assert len(steps) == 3, topic
        for d in steps:
            assert len(d) >= 10 and np.allclose(d, 0.1, atol=1e-6), (topic, d)
    clock = [t for t, _ in msgs["/clock"]]  # best effort, depth 1: may skip, never goes back
    assert len(clock) > 10 and np.all(np.diff(clock) >= 0)
    # 2 Hz: one command per control period (0.5 s) of the same tasks, plus at most one
    # immediate zero command when the prewarning / t_max stops the blade between two periods
    starts = {n: min(t for t, m in msgs["/peel/pose"] if m.header.frame_id == f"peel_task_{n}")
              for n in range(3)}
    for n in range(3):
        cmds = [(t, m) for t, m in msgs["/peel/cmd_vel"] if m.header.frame_id == f"peel_task_{n}"]
        periodic = [t for t, _ in cmds if abs((t - starts[n]) / 0.5 - round((t - starts[n]) / 0.5))
                    < 1e-6]
        extra = [m for t, m in cmds if t not in periodic]
        d = np.diff(np.unique(np.round(periodic, 6)))
        assert len(d) >= 2 and np.allclose(d, 0.5, atol=1e-6), d
        assert len(extra) <= 1 and all(m.twist.linear.x == 0.0 for m in extra)
    # every command answers a state sample at a control instant (lockstep stamps)
    state_stamps = {round(t, 6) for t, _ in msgs["/peel/pose"]}
    assert all(round(t, 6) in state_stamps for t, _ in msgs["/peel/cmd_vel"])
    for topic in ("/peel/wrench", "/peel/pose", "/peel/cmd_vel"):
        assert frame_tasks(msgs[topic]) == {0, 1, 2}, topic

    trajs = msgs["/peel/trajectory"]
    assert len(trajs) == 3
    for n, (_, m) in enumerate(trajs):
        header = json.loads(m.layout.dim[0].label.split(" ", 1)[1])
        assert header["outcome"] in ("done", "timeout", "safety_stop")
        assert header["meta"]["task_index"] == n
        rows = np.asarray(m.data).reshape(m.layout.dim[0].size, 7)
        assert np.allclose(np.diff(rows[:, 0]), 0.1)  # trajectory time restarts per task

    versions = [int(m.data) for _, m in msgs["/peel/model_version"]]
    assert versions[0] == 0
    assert versions == sorted(versions) and len(set(versions)) == len(versions)
    assert len(versions) - 1 >= 2, versions  # at least two swaps, increasing versions
    models = sorted(p.name for p in (tmp_path / "run" / "models").glob("model_v*.safetensors"))
    assert models[:2] == ["model_v0001.safetensors", "model_v0002.safetensors"]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert [r["model_version"] for r in summary["results"]] == [0, 1, 2]
    assert_clean_logs(tmp_path / "run")

    # mcap's own ROS 2 decoder reads the same bag: same messages per topic, same values
    other = read_bag_mcap_ros2(bag)
    assert {k: len(v) for k, v in other.items()} == {k: len(v) for k, v in msgs.items()}
    assert [m.wrench.force.x for m in other["/peel/wrench"]] == \
        [m.wrench.force.x for _, m in msgs["/peel/wrench"]]
    assert [m.data for m in other["/peel/model_version"]] == versions
    assert [len(m.data) for m in other["/peel/trajectory"]] == [len(m.data) for _, m in trajs]
    # channel metadata: the QoS the publishers offered and the type hash they announced
    from mcap.reader import make_reader

    with open(next(bag.glob("*.mcap")), "rb") as fh:
        channels = {c.topic: c for c in make_reader(fh).get_summary().channels.values()}
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, ch in channels.items():
        assert ch.message_encoding == "cdr"
        assert ch.metadata["topic_type_hash"] == store.hash_rihs01(_type_of(name))
        offered = yaml.safe_load(ch.metadata["offered_qos_profiles"])
        assert offered and offered[0]["reliability"] == "reliable", (name, offered)
    latched = yaml.safe_load(channels["/peel/model_version"].metadata["offered_qos_profiles"])
    assert latched[0]["durability"] == "transient_local"

    # the same three peels in one process, as `peel experiment` runs them
    from peel_experiments.experiment import Setup, planner_params, run_job

    ov = str(tmp_path / "override.yaml")
    exp = run_job("ol-mppi", 3, Setup(
        checkpoint=str(tmp_path / "init.safetensors"), tasks=3, save_model=False,
        planner_params=planner_params(planner_overrides=ov), sim_overrides=ov,
        learner_overrides=ov))["tasks"]
    for g, e in zip(summary["results"], exp, strict=True):
        assert g["outcome"] == e["outcome"]
        assert g["model_version"] == e["model_version"]
        assert abs(g["t_cpl_s"] - e["t_cpl"]) <= 0.2 + 1e-9, (g, e)
        assert abs(g["J"] - e["cost"]) <= 0.02 * max(1.0, abs(e["cost"])), (g, e)


def _type_of(topic: str) -> str:
    from peel_msgs_py.topics import topic as spec

    return spec(topic).type


def test_learner_killed_planner_keeps_last_good_model(tmp_path: Path, ros_domain: str) -> None:
    bag = tmp_path / "bag"
    # a slow learner (many meta steps per update) leaves seconds between its first swap and
    # its second, so the kill below lands mid-run whatever the machine's load
    proc = subprocess.Popen(graph_cmd(tmp_path, "--record", str(bag), "--keep-going",
                                      wait_model_s=8.0, meta_steps=150),
                            env=node_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        out = Lines(proc)
        pid = int(out.wait_for(r"started model_learner_node \(pid (\d+)\)", 60).group(1))
        first = int(out.wait_for(r"planner model v([1-9]\d*) active", 300).group(1))
        os.kill(pid, signal.SIGKILL)  # the learner dies mid-run, after its first swap
        rc = proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    stdout, stderr = out.join(), proc.stderr.read() if proc.stderr else ""
    assert rc == 1, stdout + stderr  # a node died: non-zero, and it is named
    assert "model_learner_node" in stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert len(summary["results"]) == 3, stdout  # the tasks went on without the learner
    assert not (tmp_path / "run" / "models" / "model_v0003.safetensors").exists()
    msgs = read_bag(bag)
    versions = [int(m.data) for _, m in msgs["/peel/model_version"]]
    assert versions[0] == 0 and versions == sorted(set(versions)) and first in versions
    assert versions[-1] >= 1  # at least one swap before the learner died, none after
    # the last task ran with the last model the planner accepted before it started (its last
    # good model; on a loaded machine the first update may even arrive after task 2 started)
    logs = log_times(bag)
    task3_start = min(t for t, frame in logs["/peel/pose"] if frame == "peel_task_2")
    before = [v for (t, _), v in zip(logs["/peel/model_version"], versions, strict=True)
              if t <= task3_start]
    assert summary["results"][2]["model_version"] == before[-1]
    assert summary["results"][2]["model_version"] in versions
    # ... and the planner kept planning in it
    assert frame_tasks(msgs["/peel/cmd_vel"]) == {0, 1, 2}
    assert len(msgs["/peel/trajectory"]) == 3


# An independent rclpy node, written here with rclpy and the generated classes only (none of
# our helpers): it hears /peel/wrench, then reads and sets planner parameters through the
# standard parameter services of the running graph; prints one JSON line.
INDEPENDENT = """
import json, sys, time
import rclpy
from rclpy.node import Node
from geometry_msgs.msg import WrenchStamped
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters

rclpy.init()
node = Node("independent_client")
heard = []
node.create_subscription(WrenchStamped, "/peel/wrench", lambda m: heard.append(m), 10)
srv = {name: node.create_client(kind, "/peel_planner_node/" + name) for name, kind in
       (("get_parameters", GetParameters), ("set_parameters", SetParameters),
        ("describe_parameters", DescribeParameters))}
assert all(c.wait_for_service(timeout_sec=120) for c in srv.values())
end = time.monotonic() + 120
while len(heard) < 5 and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)

def call(name, req):
    fut = srv[name].call_async(req)
    rclpy.spin_until_future_complete(node, fut, timeout_sec=60)
    return fut.result()

def get(name):
    return call("get_parameters", GetParameters.Request(names=[name])).values[0].double_value

def put(name, value):
    pv = (ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
          if isinstance(value, float) else
          ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value))
    res = call("set_parameters", SetParameters.Request(
        parameters=[Parameter(name=name, value=pv)])).results[0]
    return [res.successful, res.reason]

desc = call("describe_parameters", DescribeParameters.Request(names=["mppi.lambda"])).descriptors[0]
out = {"heard": len(heard), "frame": heard[0].header.frame_id if heard else None,
       "lambda_before": get("mppi.lambda"),
       "describe": [desc.description, desc.read_only,
                    [r.from_value for r in desc.floating_point_range]],
       "set_ok": put("mppi.lambda", 0.2), "set_range": put("mppi.lambda", -1.0),
       "set_int": put("mppi.lambda", 1), "set_read_only": put("safety.f_prewarn_n", 30.0),
       "lambda_after": get("mppi.lambda"), "prewarn_after": get("safety.f_prewarn_n")}
print(json.dumps(out), flush=True)
node.destroy_node()
rclpy.shutdown()
"""


def test_ctrl_c_independent_client_and_clean_stop(tmp_path: Path, ros_domain: str) -> None:
    """While the graph runs, an independent rclpy process hears /peel/wrench and reads and sets
    planner parameters over the standard services (refusals name the parameter, the old value
    stays); Ctrl-C then stops every node on one signal, with no traceback, and a readable bag."""
    bag = tmp_path / "bag"
    proc = subprocess.Popen(graph_cmd(tmp_path, "--record", str(bag), tasks=20),
                            env=node_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        out = Lines(proc)
        pids = [int(m) for m in re.findall(r"\(pid (\d+)\)", "\n".join(
            [out.wait_for(r"started peel_sim_node \(pid \d+\)", 60).string, *out.lines]))]
        client = subprocess.run([sys.executable, "-c", INDEPENDENT], env=node_env(),
                                capture_output=True, text=True, timeout=300)
        out.wait_for(r"task 1/20: ", 300)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert client.returncode == 0, client.stderr
    got = json.loads(client.stdout.strip().splitlines()[-1])
    assert got["heard"] >= 5 and got["frame"].startswith("peel_task_")
    assert got["lambda_before"] == 0.1
    assert "Eq. 38" in got["describe"][0] and got["describe"][1] is False
    assert got["set_ok"] == [True, ""]
    assert not got["set_range"][0] and "mppi.lambda" in got["set_range"][1]
    assert not got["set_int"][0] and "mppi.lambda" in got["set_int"][1]
    assert "type" in got["set_int"][1].lower()
    assert not got["set_read_only"][0] and "safety.f_prewarn_n" in got["set_read_only"][1]
    assert got["lambda_after"] == 0.2 and got["prewarn_after"] == 20.0  # last good values

    assert rc == 130, out.join()
    for pid in set(pids):  # every node stopped
        assert not Path(f"/proc/{pid}").exists() or \
            Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    assert_clean_logs(tmp_path / "run")
    msgs = read_bag(bag)  # a complete bag: rosbags opens it without repair
    assert len(msgs["/peel/wrench"]) >= 10
    assert len(msgs["/peel/trajectory"]) >= 1


def test_bad_parameter_is_refused_before_anything_starts(tmp_path: Path, ros_domain: str) -> None:
    """Each bad override (a wrong type, out of range, an unknown name, a misspelled node
    section) is one line naming it, exit 2, and no node was started."""
    cases = {
        "peel_planner_node:\n  ros__parameters:\n    mppi:\n      lambda: 1\n":
            "parameter 'mppi.lambda': wrong type, expected DOUBLE got INTEGER",
        "peel_planner_node:\n  ros__parameters:\n    mppi:\n      n_samples: 0\n":
            "parameter 'mppi.n_samples'",
        "peel_planner_node:\n  ros__parameters:\n    mppi:\n      n_sampels: 50\n":
            "unknown parameter 'mppi.n_sampels'",
        "model_learner_node:\n  ros__parameters:\n    train:\n      epocs: 5\n":
            "unknown parameter 'train.epocs'",
        "peel_planer_node:\n  ros__parameters:\n    mppi:\n      lambda: 0.2\n":
            "unknown node section 'peel_planer_node'",
    }
    for i, (text, expected) in enumerate(cases.items()):
        override = tmp_path / f"bad{i}.yaml"
        override.write_text(text)
        res = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "graph", "--params",
                              str(override), "--out", str(tmp_path / f"run{i}")],
                             env=node_env(), capture_output=True, text=True, timeout=120)
        assert res.returncode == 2, (text, res.stdout, res.stderr)
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and expected in lines[0], (text, res.stderr)
        assert "started" not in res.stdout


def test_node_refusing_its_parameters_exits_2_and_so_does_the_graph(tmp_path: Path,
                                                                   ros_domain: str) -> None:
    """A node that refuses its start (here the planner: a model.path that is no checkpoint)
    exits 2 with one line; the graph stops the others and exits 2 too."""
    override = tmp_path / "override.yaml"
    override.write_text(f"peel_planner_node:\n  ros__parameters:\n    model:\n"
                        f"      path: {tmp_path / 'missing.safetensors'}\n")
    res = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "graph", "--params",
                          str(override), "--out", str(tmp_path / "run"), "--tasks", "1"],
                         env=node_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stdout + res.stderr
    assert "peel_planner_node" in res.stderr and "exit status 2" in res.stderr
    log = (tmp_path / "run" / "logs" / "peel_planner_node.log").read_text()
    assert log.strip().splitlines()[-1].startswith("peel_planner_node: error: ")
    assert "parameter 'model.path'" in log and "missing" in log
    assert_clean_logs(tmp_path / "run")
