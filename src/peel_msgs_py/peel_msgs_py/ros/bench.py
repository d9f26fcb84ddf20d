"""``peel bench ros``: rclpy between two processes on this machine, as JSON.

    peel bench ros [--messages 500] [--rate 200] [--services 200]

Starts an echo process (this module with ``--echo``: a node that republishes every
``WrenchStamped`` it gets on ``/peel_bench/ping`` to ``/peel_bench/pong``), then measures from
this process:

* ``start_to_ready_s``: process start to the echo node spinning (imports, context, entities);
* ``discovery_s``: from then to the first completed round trip;
* ``pubsub_rtt_us``: publish -> echo -> back, median and p95 over ``--messages`` messages sent
  at ``--rate`` Hz (default QoS: reliable, keep_last 10, volatile); one way is about half;
* ``service_rtt_us``: ``get_parameters`` on the echo node's standard parameter service.

Same domain and discovery range as the caller (LOCALHOST unless set).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import rclpy
from geometry_msgs.msg import WrenchStamped
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node

from .. import discovery
from ..errors import PeelError
from .main import run_node

PING, PONG = "/peel_bench/ping", "/peel_bench/pong"


class EchoNode(Node):
    """Republishes every ping as a pong."""

    def __init__(self) -> None:
        super().__init__("peel_bench_echo")
        pub = self.create_publisher(WrenchStamped, PONG, 10)
        self.create_subscription(WrenchStamped, PING, pub.publish, 10)
        print("ready", flush=True)


def _quantiles(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {"median": round(statistics.median(ordered), 1),
            "p95": round(ordered[int(0.95 * (len(ordered) - 1))], 1), "n": len(ordered)}


def measure(messages: int, rate: float, services: int) -> dict[str, object]:
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", __name__, "--echo"], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None
        if proc.stdout.readline().strip() != "ready":
            raise PeelError("peel bench ros: the echo process did not start")
        ready = time.monotonic() - t0
        rclpy.init()
        node = Node("peel_bench")
        sent: dict[int, int] = {}
        rtt: list[float] = []

        def on_pong(msg: WrenchStamped) -> None:
            k = int(msg.header.stamp.sec)
            if k in sent:
                rtt.append((time.perf_counter_ns() - sent.pop(k)) / 1e3)

        node.create_subscription(WrenchStamped, PONG, on_pong, 10)
        pub = node.create_publisher(WrenchStamped, PING, 10)

        def ping(k: int) -> None:
            msg = WrenchStamped()
            msg.header.stamp.sec = k
            sent[k] = time.perf_counter_ns()
            pub.publish(msg)

        t1, k = time.monotonic(), 0
        while not rtt and time.monotonic() - t1 < 60:  # discovery: until one comes back
            ping(k)
            k += 1
            rclpy.spin_once(node, timeout_sec=0.01)
        if not rtt:
            raise PeelError("peel bench ros: no round trip within 60 s")
        discovery_s = time.monotonic() - t1
        rtt.clear()
        sent.clear()
        for i in range(messages):
            ping(1_000_000 + i)
            end = time.monotonic() + 1.0 / rate
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=max(0.0, end - time.monotonic()))
        end = time.monotonic() + 2.0
        while sent and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.01)
        client = node.create_client(GetParameters, "/peel_bench_echo/get_parameters")
        client.wait_for_service(timeout_sec=30)
        srv: list[float] = []
        for _ in range(services):
            t = time.perf_counter_ns()
            fut = client.call_async(GetParameters.Request(names=["use_sim_time"]))
            rclpy.spin_until_future_complete(node, fut, timeout_sec=10)
            srv.append((time.perf_counter_ns() - t) / 1e3)
        node.destroy_node()
        rclpy.try_shutdown()
        return {"benchmark": "ros", "rmw": "rmw_fastrtps_cpp (rclpy " + _rclpy_version() + ")",
                "start_to_ready_s": round(ready, 3), "discovery_s": round(discovery_s, 3),
                "pubsub_rtt_us": _quantiles(rtt), "lost": len(sent),
                "service_rtt_us": _quantiles(srv)}
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=30)


def _rclpy_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    for dist in ("ros-rclpy", "rclpy"):
        try:
            return version(dist)
        except PackageNotFoundError:
            continue
    return "system"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="peel bench ros", description=__doc__.split("\n\n")[0])
    p.add_argument("--messages", type=int, default=500)
    p.add_argument("--rate", type=float, default=200.0)
    p.add_argument("--services", type=int, default=200)
    p.add_argument("--echo", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.echo:
        return run_node("peel_bench_echo", EchoNode, None)
    if args.messages < 1 or args.services < 1 or not args.rate > 0:
        raise PeelError("--messages and --services must be >= 1, --rate > 0")
    discovery.confine()
    print(json.dumps(measure(args.messages, args.rate, args.services)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
