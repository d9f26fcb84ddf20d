"""The node graph as separate processes on the embedded runtime (issue 7).

Each test starts ``peel graph`` (three node processes + recorder) on its own ROS_DOMAIN_ID with a
small parameter override (short tasks, small N/H, one meta step) and reads the bag back with
``rosbags`` (its own rosbag2 reader and Jazzy typestore, not our bag code).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

ROOT = Path(__file__).resolve().parents[1]
SLOT_S = 20.0  # node.task_slot_s in the override: task i starts at ROS time i * SLOT_S

OVERRIDE = f"""
/**:
  ros__parameters:
    task:
      q_ter_mm: 6.0
      t_max_s: 8.0
peel_sim_node:
  ros__parameters:
    node:
      task_slot_s: {SLOT_S}
      cmd_timeout_s: 5.0
      wait_model_s: {{wait_model_s}}
peel_planner_node:
  ros__parameters:
    model:
      path: {{init}}
    mppi:
      n_samples: 16
      horizon: 3
model_learner_node:
  ros__parameters:
    node:
      init_model: {{init}}
    maml:
      meta_steps: {{meta_steps}}
      support_slices: 4
      query_slices: 4
      eval_slices: 4
      m: 2
peel_bringup:
  ros__parameters:
    graph:
      final_model_wait_s: 120.0
"""


def domain_id(offset: int) -> str:
    """A ROS_DOMAIN_ID unique to this test (and to this pytest process)."""
    return str(120 + (os.getpid() % 20) * 5 + offset)


def initial_model(tmp: Path) -> Path:
    """A freshly initialised forward model (seeded): the tests do not depend on training."""
    import torch

    from model_learner_node.checkpoint import save_checkpoint
    from model_learner_node.config import ModelConfig
    from model_learner_node.predictor import ForcePredictor

    torch.manual_seed(0)
    return save_checkpoint(tmp / "init.safetensors", ForcePredictor(ModelConfig()))


def write_override(tmp: Path, wait_model_s: float, meta_steps: int = 1) -> Path:
    path = tmp / "override.yaml"
    path.write_text(OVERRIDE.replace("{wait_model_s}", str(wait_model_s))
                    .replace("{meta_steps}", str(meta_steps))
                    .replace("{init}", str(initial_model(tmp))))
    return path


def graph_cmd(tmp: Path, *extra: str, tasks: int = 3, wait_model_s: float = 120.0,
              plant: str = "sim", meta_steps: int = 1) -> list[str]:
    return [sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", plant, "--tasks",
            str(tasks), "--params", str(write_override(tmp, wait_model_s, meta_steps)),
            "--out", str(tmp / "run"), "--seed", "3", *extra]


def graph_env(offset: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(PEEL_RUNTIME="dds", ROS_DOMAIN_ID=domain_id(offset), PYTHONUNBUFFERED="1")
    return env


class Lines:
    """Collect a child's stdout lines in a thread; wait for a pattern."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.lines: list[str] = []
        self.proc = proc
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, pattern: str, timeout: float) -> re.Match[str]:
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.lines):
                m = rx.search(line)
                if m:
                    return m
            if self.proc.poll() is not None and not self._t.is_alive():
                break
            time.sleep(0.1)
        raise AssertionError(f"no line matching {pattern!r}; got:\n" + "\n".join(self.lines))

    def join(self) -> str:
        self._t.join(timeout=10)
        return "\n".join(self.lines)


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


def per_task_steps(stamps: list[float]) -> list[np.ndarray]:
    """Differences of the (unique, sorted) stamps inside each task slot of ROS time."""
    t = np.unique(np.round(np.asarray(stamps), 6))
    slots = np.floor(t / SLOT_S + 1e-9).astype(int)
    return [np.diff(t[slots == s]) for s in np.unique(slots)]


def frame_tasks(msgs: list[tuple[float, object]]) -> set[int]:
    """Task indices named by the header frame ids (peel_task_<k>)."""
    return {int(m.header.frame_id.rsplit("_", 1)[1]) for _, m in msgs}


def test_three_tasks_bag_rates_trajectories_and_model_swaps(tmp_path: Path) -> None:
    """On the plant, seed 3; also the same results as ``peel experiment`` (run_job) with the
    same seed, model and parameters (issue 7 section 4)."""
    bag = tmp_path / "bag"
    res = subprocess.run(graph_cmd(tmp_path, "--record", str(bag), plant="plant"),
                         env=graph_env(0), capture_output=True, text=True, timeout=400)
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

    # the same three peels in one process, as `peel experiment` runs them
    from peel_bringup.experiment import Setup, planner_params, run_job

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


def test_learner_killed_planner_keeps_last_good_model(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    # a slow learner (many meta steps per update) leaves seconds between its first swap and
    # its second, so the kill below lands mid-run whatever the machine's load
    proc = subprocess.Popen(graph_cmd(tmp_path, "--record", str(bag), "--keep-going",
                                      wait_model_s=8.0, meta_steps=150),
                            env=graph_env(1), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
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
    # the last task ran with the last model the planner accepted (its last good model) ...
    assert summary["results"][2]["model_version"] == versions[-1] >= 1
    # ... and the planner kept planning in it
    assert frame_tasks(msgs["/peel/cmd_vel"]) == {0, 1, 2}
    assert len(msgs["/peel/trajectory"]) == 3


def test_ctrl_c_leaves_a_readable_bag(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    proc = subprocess.Popen(graph_cmd(tmp_path, "--record", str(bag), tasks=20),
                            env=graph_env(2), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        out = Lines(proc)
        pids = [int(m) for m in re.findall(r"\(pid (\d+)\)", "\n".join(
            [out.wait_for(r"started peel_sim_node \(pid \d+\)", 60).string, *out.lines]))]
        out.wait_for(r"task 1/20: ", 300)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 130, out.join()
    for pid in set(pids):  # every node stopped
        assert not Path(f"/proc/{pid}").exists() or \
            Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    msgs = read_bag(bag)  # a complete bag: rosbags opens it without repair
    assert len(msgs["/peel/wrench"]) >= 10
    assert len(msgs["/peel/trajectory"]) >= 1
