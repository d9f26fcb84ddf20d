"""``peel graph --plant nachi``: the whole graph against ``peel nachi-emulator`` (real processes:
the emulator, the launcher, the bridge on rclpy, the planner, the learner and the recorder on the
embedded runtime), with the bag read back by ``rosbags``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from nachi_rig import domain_id, ros_env

from peel_msgs_py import bagread, topics

OVERRIDE = """
peel_planner_node:
  ros__parameters:
    mppi:
      n_samples: 16
      horizon: 3
model_learner_node:
  ros__parameters:
    maml:
      meta_steps: 1
      support_slices: 4
      query_slices: 4
      eval_slices: 4
      m: 2
peel_nachi_bridge:
  ros__parameters:
    safety:
      stall_timeout_s: 1.0   # seven processes on two cores; the 300 ms rule has its own tests
"""


def test_graph_runs_against_the_emulator(tmp_path: Path) -> None:
    env = ros_env(domain_id(6))
    emu = subprocess.Popen([sys.executable, "-m", "peel_bringup.cli", "nachi-emulator", "--port",
                            "0", "--plant", "plant", "--seed", "4"], env=env,
                           stdout=subprocess.PIPE, text=True)
    try:
        first = emu.stdout.readline()  # type: ignore[union-attr]
        port = first.split(":")[1].split()[0]
        override = tmp_path / "override.yaml"
        override.write_text(OVERRIDE)
        cmd = [sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", "nachi",
               "--nachi-port", port, "--tasks", "2", "--seed", "4", "--params", str(override),
               "--record", str(tmp_path / "bag"), "--out", str(tmp_path / "run")]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    finally:
        emu.terminate()
        emu.wait(timeout=30)
    logs = tmp_path / "run" / "logs"
    bridge_log = (logs / "peel_nachi_bridge.log").read_text() if logs.is_dir() else ""
    assert out.returncode == 0, out.stdout + out.stderr + bridge_log[-2000:]
    assert "task 2/2:" in out.stdout
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["plant"] == "nachi" and len(summary["results"]) == 2
    trajs = bagread.read_trajectories(tmp_path / "bag")
    assert [t.meta["source"] for t in trajs] == ["nachi", "nachi"]
    assert [t.meta["controller_task_id"] for t in trajs] == [0, 1]
    assert trajs[1].meta["model_version"] >= 1  # the learner's update planned task 2
    arrays = bagread.read_topics(tmp_path / "bag")
    assert len(arrays[topics.CMD_VEL]["u_mmps"]) > 0 and len(arrays[topics.CLOCK]["t_s"]) > 0
    assert "connected to controller EMU-MZ04" in bridge_log


def test_nachi_options_need_the_nachi_plant(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", "sim",
                          "--nachi-port", "48100", "--out", str(tmp_path / "run")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert out.stderr.strip() == ("peel graph: error: --nachi-host / --nachi-port need "
                                  "--plant nachi")
