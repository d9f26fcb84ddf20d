"""``peel bench ros``: rclpy round trips between two real processes, one JSON object."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh


def test_bench_ros_prints_round_trips(ros_domain: str) -> None:
    res = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "bench", "ros", "--messages",
                          "30", "--rate", "100", "--services", "5"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    assert report["benchmark"] == "ros" and report["rmw"].startswith("rmw_fastrtps_cpp")
    assert report["pubsub_rtt_us"]["n"] + report["lost"] == 30 and report["lost"] <= 3
    assert report["service_rtt_us"]["n"] == 5
    assert 0 < report["pubsub_rtt_us"]["median"] <= report["pubsub_rtt_us"]["p95"]
    assert report["start_to_ready_s"] > 0 and report["discovery_s"] >= 0


def test_bench_ros_bad_arguments() -> None:
    res = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "bench", "ros", "--messages",
                          "0"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "--messages" in res.stderr and "Traceback" not in res.stderr
