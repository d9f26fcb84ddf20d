"""What the tests that start node processes share: their environment, their parameter override
files (:func:`override_yaml` and the settings most of them use), a small learner update, and a
bag read back by mcap's own ROS 2 decoder (``mcap-ros2-support``, independent of ours)."""

from __future__ import annotations

import os
import re
import subprocess
import textwrap
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

# The learner's Algorithm 1 cut down to one meta step on a few slices, every update offered
# unchecked (gate.holdout 0): the tests check the traffic and the swap, not what an update
# learns (test_model_gate.py checks the gate).
SMALL_LEARNER: dict[str, Any] = {
    "maml": {"meta_steps": 1, "support_slices": 4, "query_slices": 4, "eval_slices": 4, "m": 2},
    "gate": {"holdout": 0.0},
}
# The same as YAML text, indented to sit under ``ros__parameters:``.
SMALL_MAML = textwrap.indent(yaml.safe_dump(SMALL_LEARNER, sort_keys=False), "    ")

# What every graph test's override holds: a small planner (N = 16 samples over H = 3 steps)
# and the small learner update above.
FAST: dict[str, Any] = {
    "peel_planner_node": {"mppi": {"n_samples": 16, "horizon": 3}},
    "model_learner_node": SMALL_LEARNER,
}
# A graph on a ROS domain of its own (the ``ros_domain`` fixture): a short look for another graph.
ALONE: dict[str, Any] = {"peel_bringup": {"graph": {"alone_wait_s": 0.5}}}
# Short simulator tasks, one every 20 s of ROS time.
SIM_TASKS: dict[str, Any] = {
    "/**": {"task": {"q_ter_mm": 6.0, "t_max_s": 8.0}},
    "peel_sim_node": {"node": {"task_slot_s": 20.0, "cmd_timeout_s": 5.0}},
}


def merged(*layers: Mapping[str, Any]) -> dict[str, Any]:
    """The layers deep-merged left to right: a later value replaces an earlier one, nested
    dicts merge key by key; the layers themselves are not changed."""
    out: dict[str, Any] = {}
    for layer in layers:
        for key, value in layer.items():
            if isinstance(value, Mapping):
                earlier = out.get(key)
                out[key] = merged(earlier, value) if isinstance(earlier, dict) else merged(value)
            else:
                out[key] = str(value) if isinstance(value, os.PathLike) else value
    return out


def override_yaml(*layers: Mapping[str, Mapping[str, Any]]) -> str:
    """A ROS 2 parameter file's text: node name (or ``/**``) -> its parameters as nested dicts,
    the layers deep-merged (:func:`merged`), each node's under ``ros__parameters``; paths are
    written as strings."""
    nodes = merged(*layers)
    return yaml.safe_dump({node: {"ros__parameters": params} for node, params in nodes.items()},
                          sort_keys=False, width=1 << 16)


def node_env() -> dict[str, str]:
    """The environment of the processes a test starts: its ROS domain (set by the conftest or
    the ``ros_domain`` fixture) and unbuffered output, so their lines arrive as printed."""
    return dict(os.environ, PYTHONUNBUFFERED="1")


def read_bag_mcap_ros2(bag: Path) -> dict[str, list[object]]:
    """topic -> decoded messages of the bag folder's one MCAP file."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list[object]] = {}
    (path,) = sorted(bag.glob("*.mcap"))
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append(msg)
    return out


def assert_clean_logs(run_dir: Path) -> None:
    """Every node stopped on one signal, cleanly: no traceback in any log of the run."""
    logs = sorted((run_dir / "logs").glob("*.log"))
    assert len(logs) >= 3
    for log in logs:
        text = log.read_text(errors="replace")
        assert "Traceback" not in text and "KeyboardInterrupt" not in text, (log.name, text[-2000:])


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
