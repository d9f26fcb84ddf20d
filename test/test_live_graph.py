"""The live view of a running graph (``peel graph --live PORT``, docs/graph.md "Live view").

One short graph run (one task of 6 mm on the simulator, small N/H) with ``--live``: a client of
the Foxglove WebSocket protocol written for the test (:mod:`foxglove_client`, the standard
library alone) connects while it runs, reads ``serverInfo`` and ``advertise``, subscribes to
the force channel and receives its ``messageData`` frames: force samples 0.1 s of simulated time
apart (their header stamps), F_RX and F_RZ finite, the same samples as the run's bag holds on the
same topic (what lets one layout show both). The server listens on 127.0.0.1 only.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_client import SUBPROTOCOLS, connect, message_data
from graph_helpers import Lines, assert_clean_logs, node_env
from test_graph_run import read_bag, write_override

pytestmark = pytest.mark.process  # starts processes: scripts/flaky.sh

#: Sample period of the state streams, s of simulated time (topics.STATE_RATE_HZ = 10 Hz).
DT_S = 0.1


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def listening_addresses(port: int) -> set[str]:
    """The local IPv4 addresses of sockets listening on ``port`` (/proc/net/tcp, state 0A)."""
    out = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        addr, _, hexport = local.partition(":")
        if state == "0A" and int(hexport, 16) == port:
            out.add(socket.inet_ntoa(bytes.fromhex(addr)[::-1]))
    return out


def read_forces(port: int, timeout_s: float) -> tuple[dict, dict, list[dict]]:
    """Connect (retrying until the server is up), subscribe to /peel/wrench and collect its
    messages until the server goes away with the graph; (serverInfo, the channel, messages)."""
    client = connect("127.0.0.1", port, timeout_s)
    info, channels, got = None, {}, []
    deadline = time.monotonic() + timeout_s
    try:
        assert client.headers.get("sec-websocket-protocol") in SUBPROTOCOLS
        while time.monotonic() < deadline:
            try:
                kind, msg = client.recv()
            except TimeoutError:
                continue  # nothing for a while: the graph is starting
            except (ConnectionError, OSError):
                break  # the graph stopped, and its live view with it
            if kind == "text" and msg["op"] == "serverInfo":
                info = msg
            elif kind == "text" and msg["op"] == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
                if "/peel/wrench" in channels:
                    client.subscribe({1: channels["/peel/wrench"]["id"]})
            elif kind == "binary":
                sid, log_ns, data = message_data(msg)
                assert sid == 1
                got.append({"log_ns": log_ns, **json.loads(data)})
    finally:
        client.close()
    return info, channels["/peel/wrench"], got


def test_live_view_serves_force_samples_at_10_hz_of_sim_time(tmp_path: Path,
                                                             ros_domain: str) -> None:
    port = free_port()
    cmd = [sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", "sim", "--tasks", "1",
           "--params", str(write_override(tmp_path, 120.0)), "--out", str(tmp_path / "run"),
           "--seed", "3", "--live", str(port), "--record", str(tmp_path / "bag")]
    proc = subprocess.Popen(cmd, env=node_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        out = Lines(proc)
        out.wait_for(r"started peel_live \(pid \d+\)", 60)
        addresses: set[str] = set()
        for _ in range(50):  # the server is up once peel_live says so in its log
            if (addresses := listening_addresses(port)):
                break
            time.sleep(0.2)
        info, channel, got = read_forces(port, timeout_s=240)
        rc = proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    log = out.join()
    assert rc == 0, log
    assert f"live view on ws://127.0.0.1:{port}" in log
    assert addresses == {"127.0.0.1"}  # this machine only
    assert info is not None and info["name"] == "peel"
    assert channel["encoding"] == "json" and channel["schemaEncoding"] == "jsonschema"
    assert channel["schemaName"] == "geometry_msgs/msg/WrenchStamped"
    assert "wrench" in json.loads(channel["schema"])["properties"]
    assert len(got) >= 10, log
    frames = {m["header"]["frame_id"] for m in got}
    assert all(f.startswith("peel_task_") for f in frames)
    stamps = np.array([m["header"]["stamp"]["sec"] + m["header"]["stamp"]["nanosec"] * 1e-9
                       for m in got])
    # the log time of each frame is the sample's stamp: the view runs on the graph's clock
    assert [m["log_ns"] for m in got] == [m["header"]["stamp"]["sec"] * 10**9
                                          + m["header"]["stamp"]["nanosec"] for m in got]
    steps = np.diff(np.unique(np.round(stamps, 6)))  # a re-sent sample repeats its stamp
    assert len(steps) >= 8
    assert np.allclose(steps, DT_S, atol=1e-6), steps
    forces = np.array([[m["wrench"]["force"]["x"], m["wrench"]["force"]["z"]] for m in got])
    assert np.all(np.isfinite(forces)) and np.any(forces != 0.0)
    bag = {(round(t, 6), m.wrench.force.x, m.wrench.force.z)
           for t, m in read_bag(tmp_path / "bag")["/peel/wrench"]}
    live = {(round(float(t), 6), f[0], f[1]) for t, f in zip(stamps, forces, strict=True)}
    assert live <= bag
    assert_clean_logs(tmp_path / "run")
