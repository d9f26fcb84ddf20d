"""Service round trips between two OS processes, and parameters set over DDS from outside.

A server process offers ``/peel/ping`` (std_srvs/srv/Trigger) and declares parameters with a
range and an on-set callback that refuses some values. This test process is the client: it
calls the service, and sets, reads and lists the server's parameters through the standard
``/param_server/set_parameters`` (rcl_interfaces/srv/SetParameters) ... services, as
``ros2 param set`` does.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

os.environ["PEEL_RUNTIME"] = "dds"

from peel_msgs_py.runtime import Node, Parameter, rclpy
from peel_msgs_py.runtime.msg import ParameterType
from peel_msgs_py.runtime.srv import (
    GetParameters,
    ListParameters,
    SetParameters,
    Trigger,
)

SERVER = r"""
import sys
from peel_msgs_py.runtime import ExternalShutdownException, Node, SetParametersResult, rclpy
from peel_msgs_py.runtime.msg import FloatingPointRange, ParameterDescriptor
from peel_msgs_py.runtime.srv import Trigger

rclpy.init(args=sys.argv)
node = Node("param_server")
node.declare_parameter("model.path", "start.safetensors")
node.declare_parameter(
    "gain", 1.0,
    ParameterDescriptor(floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10.0)]))
node.declare_parameter("horizon", 5)
calls = [0]

def ping(request, response):
    calls[0] += 1
    response.success = True
    response.message = f"pong {calls[0]} gain={node.get_parameter('gain').value}"
    return response

def on_set(params):
    for p in params:
        if p.name == "model.path" and not p.value.endswith(".safetensors"):
            return SetParametersResult(
                successful=False, reason=f"model.path must name a .safetensors file: {p.value}")
    return SetParametersResult(successful=True)

node.add_on_set_parameters_callback(on_set)
node.create_service(Trigger, "/peel/ping", ping)
print("server ready", flush=True)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
print("server clean exit", flush=True)
"""


@pytest.fixture
def server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    domain = str(10 + (os.getpid() * 3 + 7) % 200)
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    script = tmp_path / "server.py"
    script.write_text(SERVER)
    proc = subprocess.Popen(
        [sys.executable, str(script), "--ros-args", "-p", "horizon:=8"],
        env=dict(os.environ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert "server ready" in proc.stdout.readline(), proc.stderr.read()
    rclpy.init()
    node = Node("client")
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert "server clean exit" in out


def _call(node: Node, client, request, timeout: float = 20.0):
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    assert future.done(), f"no reply from {client.srv_name}"
    return future.result()


def test_service_round_trip_between_processes(server: Node) -> None:
    client = server.create_client(Trigger, "/peel/ping")
    assert client.wait_for_service(timeout_sec=20.0)
    replies = [_call(server, client, Trigger.Request()) for _ in range(3)]
    assert [r.message for r in replies] == [f"pong {i} gain=1.0" for i in (1, 2, 3)]
    assert all(r.success for r in replies)
    # concurrent requests are told apart by their sequence numbers
    futures = [client.call_async(Trigger.Request()) for _ in range(3)]
    end = time.monotonic() + 20
    while not all(f.done() for f in futures) and time.monotonic() < end:
        rclpy.spin_once(server, timeout_sec=0.1)
    assert sorted(f.result().message for f in futures) == [
        f"pong {i} gain=1.0" for i in (4, 5, 6)
    ]


def test_parameters_set_over_dds_from_another_process(server: Node) -> None:
    set_cli = server.create_client(SetParameters, "/param_server/set_parameters")
    get_cli = server.create_client(GetParameters, "/param_server/get_parameters")
    list_cli = server.create_client(ListParameters, "/param_server/list_parameters")
    for c in (set_cli, get_cli, list_cli):
        assert c.wait_for_service(timeout_sec=20.0)

    req = SetParameters.Request(
        parameters=[
            Parameter("model.path", value="/models/v2.safetensors").to_parameter_msg(),
            Parameter("gain", value=2.5).to_parameter_msg(),
            Parameter("model.path", value="/models/v3.pt").to_parameter_msg(),
            Parameter("gain", value=50.0).to_parameter_msg(),
            Parameter("gain", value="fast").to_parameter_msg(),
            Parameter("horizon", value=2.0).to_parameter_msg(),
            Parameter("no_such", value=1).to_parameter_msg(),
        ]
    )
    results = _call(server, set_cli, req).results
    assert [r.successful for r in results] == [True, True, False, False, False, False, False]
    assert results[2].reason == "model.path must name a .safetensors file: /models/v3.pt"
    assert "'gain'" in results[3].reason and "out of range" in results[3].reason
    assert "'gain'" in results[4].reason and "expected 'DOUBLE' got 'STRING'" in results[4].reason
    assert "'horizon'" in results[5].reason and "expected 'INTEGER'" in results[5].reason
    assert "'no_such'" in results[6].reason and "not been declared" in results[6].reason

    got = _call(
        server, get_cli, GetParameters.Request(names=["model.path", "gain", "horizon", "nope"])
    ).values
    assert got[0].type == ParameterType.PARAMETER_STRING
    assert got[0].string_value == "/models/v2.safetensors"  # the refused v3 left it unchanged
    assert (got[1].type, got[1].double_value) == (ParameterType.PARAMETER_DOUBLE, 2.5)
    assert (got[2].type, got[2].integer_value) == (ParameterType.PARAMETER_INTEGER, 8)  # -p
    assert got[3].type == ParameterType.PARAMETER_NOT_SET

    listed = _call(server, list_cli, ListParameters.Request()).result
    assert {"model.path", "gain", "horizon", "use_sim_time"} <= set(listed.names)
    assert "model" in listed.prefixes

    # the service callback sees the new value
    ping = server.create_client(Trigger, "/peel/ping")
    assert ping.wait_for_service(timeout_sec=20.0)
    assert _call(server, ping, Trigger.Request()).message.endswith("gain=2.5")


def test_ros_discovery_info_names_the_server_node(server: Node) -> None:
    """What ``ros2 node list`` reads: the server's participant announces its node and entities."""
    from cyclonedds.sub import DataReader

    from peel_msgs_py.runtime.embedded.discovery import QOS, TOPIC
    from peel_msgs_py.runtime.embedded.messages import ParticipantEntitiesInfo
    from peel_msgs_py.runtime.embedded.qos import to_dds

    ctx = server.context
    reader = DataReader(
        ctx.participant, ctx.topic(TOPIC, ParticipantEntitiesInfo), qos=to_dds(QOS, writer=False)
    )
    own = ctx.participant.get_guid().bytes
    found = {}
    end = time.monotonic() + 20
    while "param_server" not in found and time.monotonic() < end:
        for info in reader.take(N=10):
            for node in info.node_entities_info_seq:
                found[node.node_name] = (bytes(info.gid.data), node)
        time.sleep(0.05)
    gid, node = found["param_server"]
    assert gid != own and node.node_namespace == "/"
    # 4 parameter services + /peel/ping: one reader and one writer each; + /parameter_events
    assert (len(node.reader_gid_seq), len(node.writer_gid_seq)) == (5, 6)
    assert len({bytes(g.data) for g in node.writer_gid_seq}) == 6
    assert all(bytes(g.data)[:12] == gid[:12] for g in node.writer_gid_seq)  # same participant
