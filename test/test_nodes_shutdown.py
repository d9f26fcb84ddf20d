"""A node stops on one signal with a clean exit and no traceback, even when a second signal
arrives during its teardown (docs/graph.md, "Failure handling"); ``peel graph`` sends each
node one SIGINT (test_graph_run.py checks every log of its runs)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest


def _start(module: str, *args: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", module, "--ros-args", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    deadline = time.monotonic() + 120
    for line in proc.stdout:
        if "ready" in line or time.monotonic() > deadline:
            break
    return proc


@pytest.mark.parametrize("module,signals", [
    ("peel_planner_node.node", (signal.SIGINT,)),
    ("peel_planner_node.node", (signal.SIGINT, signal.SIGINT)),
    ("peel_sim_node.node", (signal.SIGTERM,)),
    ("peel_sim_node.node", (signal.SIGINT, signal.SIGTERM)),
])
def test_signal_stops_the_node_cleanly(module: str, signals: tuple[int, ...],
                                       ros_domain: str) -> None:
    proc = _start(module, "-p", "mppi.n_samples:=8") if "planner" in module else _start(module)
    for sig in signals:
        proc.send_signal(sig)
        time.sleep(0.02)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "KeyboardInterrupt" not in out, out
