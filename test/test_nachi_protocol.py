"""NACHI-PEEL 1 as code: the line grammar, the splitter's 256-byte limit, the controller's
logic without sockets, the emulator's TCP behaviour, faults and the bridge's parameters."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from peel_msgs_py.errors import ParameterError, PeelError
from peel_msgs_py.params import load_param_file
from peel_nachi_bridge import protocol as p
from peel_nachi_bridge.config import BRIDGE_SPECS, BridgeConfig, load_config
from peel_nachi_bridge.parameters import NODE_NAME
from peel_nachi_emulator.emulator import ControllerEmulator, EmulatorOptions
from peel_nachi_emulator.faults import parse_fault
from peel_nachi_emulator.robot import Robot
from peel_sim_node.config import load_sim_config

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------ grammar
@pytest.mark.parametrize("msg", [
    p.Hello("NACHI-PEEL", 1, "MZ04-CTRL-1"), p.OkStart(7), p.OkStop(),
    p.Sample(1.2, 3.4567, -0.25, 19.999, 0.0), p.Done(5.3, "reached"),
    p.Alarm(10, "watchdog"), p.Err(21, "V out of range 0..20 mm/s: 25.0000"), p.Pong(12.5)])
def test_controller_messages_round_trip(msg: object) -> None:
    assert p.parse_controller(msg.line()) == msg  # type: ignore[attr-defined]


@pytest.mark.parametrize("msg", [p.Start(), p.Velocity(4.25), p.Stop(), p.Ping()])
def test_bridge_messages_round_trip(msg: object) -> None:
    assert p.parse_bridge(msg.line()) == msg  # type: ignore[attr-defined]


def test_crlf_and_extra_spaces_are_accepted() -> None:
    assert p.parse_controller(b"S 0.100  0.1480 1.48 2.05 1.61\r\n") == p.Sample(
        0.1, 0.148, 1.48, 2.05, 1.61)
    assert p.parse_controller(b"ERR 21 V out of  range\n") == p.Err(21, "V out of  range")


@pytest.mark.parametrize(("line", "kind"), [
    (b"S 0.1 1 2 nan 4\n", p.NON_FINITE), (b"S 0.1 1 2 inf 4\n", p.NON_FINITE),
    (b"S 0.1 1 2 -Infinity 4\n", p.NON_FINITE), (b"S 0.1 1 2 1e3 4\n", p.MALFORMED),
    (b"S 0.1 1 2 +3 4\n", p.MALFORMED), (b"S 0.1 1 2 3,5 4\n", p.MALFORMED),
    (b"S 0.1 1 2 .5 4\n", p.MALFORMED), (b"S 0.1 1 2 3\n", p.MALFORMED),
    (b"S 0.1 1 2 3 4 5\n", p.MALFORMED), (b"S\t0.1 1 2 3 4\n", p.MALFORMED),
    (b"S 0.1 1 2 3 \xc3\xa9\n", p.MALFORMED), (b"\n", p.MALFORMED), (b"s 0.1 1 2 3 4\n", p.MALFORMED),
    (b"DONE 1.0 finished\n", p.MALFORMED), (b"OK GO\n", p.MALFORMED), (b"ERR x text\n", p.MALFORMED),
    (b"HELLO NACHI-PEEL 1 two words\n", p.MALFORMED), (b"ALARM 10\n", p.MALFORMED)])
def test_strict_parsing(line: bytes, kind: str) -> None:
    with pytest.raises(p.LineError) as err:
        p.parse_controller(line)
    assert err.value.kind == kind


def test_bridge_side_parsing_is_strict_too() -> None:
    with pytest.raises(p.LineError):
        p.parse_bridge(b"V 4 5\n")
    with pytest.raises(p.LineError):
        p.parse_bridge(b"V nan\n")
    with pytest.raises(ValueError):
        p.Velocity(float("inf")).line()


def test_splitter_keeps_lines_up_to_256_bytes() -> None:
    s = p.LineSplitter()
    ok = b"S " + b"1" * (p.MAX_LINE - 3) + b"\n"  # exactly 256 bytes with the terminator
    too_long = b"S " + b"1" * (p.MAX_LINE - 2) + b"\n"  # 257
    s.feed(ok + too_long + b"PONG 1.0\n")
    assert s.pop() == ok
    assert s.pop() == p.OVERSIZE
    assert s.pop() == b"PONG 1.0\n"
    assert s.pop() is None


def test_splitter_drops_an_endless_line_in_pieces_and_recovers() -> None:
    s = p.LineSplitter()
    s.feed(b"x" * 200)
    assert s.pop() is None
    s.feed(b"x" * 200)
    assert s.pop() == p.OVERSIZE  # once, as soon as it is too long
    s.feed(b"x" * 5000)
    assert s.pop() is None
    s.feed(b"yy\nOK STOP\n")
    assert s.pop() == b"OK STOP\n" and s.pop() is None


# ------------------------------------------------------------------------------ controller logic
@pytest.fixture(scope="module")
def robot() -> Robot:
    r = Robot(source="sim", seed=5, cfg=load_sim_config({"task.q_ter_mm": 3.0}))
    yield r
    r.close()


def test_robot_task_cycle(robot: Robot) -> None:
    assert robot.command(p.Velocity(2.0), 0.0) == [p.Err(p.ERR_NO_TASK, "no task running")]
    ok, first = robot.command(p.Start(), 0.0)
    assert ok == p.OkStart(robot.tasks_started - 1) and first.t == 0.0 and first.q == 0.0
    assert robot.command(p.Start(), 0.0) == [p.Err(p.ERR_TASK_RUNNING, "task running")]
    assert robot.command(p.Velocity(20.5), 0.0)[0].code == p.ERR_RANGE
    assert robot.command(p.Velocity(-0.1), 0.0)[0].code == p.ERR_RANGE
    assert robot.command(p.Velocity(5.0), 0.0) == []
    ends: list[object] = []
    while robot.running:
        if round(robot.t * 10) % 5 == 0:
            robot.command(p.Velocity(5.0), robot.t)
        ends = robot.tick()
    assert isinstance(ends[-1], p.Done) and ends[-1].reason == "reached"
    assert ends[0].q >= 3.0
    assert robot.command(p.Stop(), 9.9) == [p.OkStop()]  # idle: idempotent


def test_robot_watchdog_stop_and_ping(robot: Robot) -> None:
    robot.command(p.Start(), 0.0)
    robot.command(p.Velocity(1.0), 0.0)
    out: list[object] = []
    while not out or not isinstance(out[-1], p.Done):
        out = robot.tick()
    assert out[1:] == [p.Alarm(p.ALARM_WATCHDOG, "watchdog"), p.Done(1.0, "alarm")]
    robot.command(p.Start(), 0.0)
    robot.command(p.Velocity(1.0), 0.0)
    robot.tick()
    assert robot.command(p.Ping(), 0.15) == [p.Pong(0.15)]
    assert robot.command(p.Stop(), 0.15) == [p.OkStop(), p.Done(0.15, "stopped")]
    assert not robot.running and robot.tick() == []


def test_a_refused_v_keeps_the_speed_and_feeds_the_watchdog(robot: Robot) -> None:
    robot.command(p.Start(), 0.0)
    robot.command(p.Velocity(1.0), 0.0)
    out: list[object] = []
    while not out or not isinstance(out[-1], p.Done):
        if abs(robot.t - 0.6) < 1e-9:
            assert robot.command(p.Velocity(25.0), robot.t)[0].code == p.ERR_RANGE
        out = robot.tick()
    assert robot.u == 1.0  # the refused command did not change the speed
    assert out[-1] == p.Done(1.6, "alarm")  # 1.0 s after the refused V, not after the last good one


# ------------------------------------------------------------------------------------ emulator
class Reader:
    """Lines from a socket, keeping partial lines between calls."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock, self.split = sock, p.LineSplitter()
        sock.settimeout(0.2)

    def lines(self, n: int, until: bytes | None = None, timeout_s: float = 120.0) -> list[bytes]:
        out: list[bytes] = []
        end = time.monotonic() + timeout_s
        while len(out) < n and (until is None or until not in out) and time.monotonic() < end:
            while len(out) < n and (line := self.split.pop()) is not None:
                out.append(line)  # type: ignore[arg-type]
            if len(out) < n:
                try:
                    self.split.feed(self.sock.recv(4096))
                except TimeoutError:
                    continue
        return out


def test_emulator_over_tcp() -> None:
    emu = ControllerEmulator(EmulatorOptions(port=0, speed=5.0, controller_id="EMU-T"),
                             robot=Robot(cfg=load_sim_config({"task.q_ter_mm": 4.0})),
                             log=lambda text: None).start()
    try:
        with socket.create_connection(("127.0.0.1", emu.port)) as a:
            ra = Reader(a)
            assert ra.lines(1) == [b"HELLO NACHI-PEEL 1 EMU-T\n"]
            with socket.create_connection(("127.0.0.1", emu.port)) as b:  # one client at a time
                assert Reader(b).lines(1) == [b"ERR 31 busy: another client is connected\n"]
            a.sendall(b"PING\nV 1 2\nFLY\nV nan\n" + b"x" * 300 + b"\nSTART\nV 4.0\n")
            got = ra.lines(10)
            assert got[0].startswith(b"PONG ")
            assert got[1:5] == [b"ERR 11 syntax: V takes 1 fields, got 2\n",
                                b"ERR 11 syntax: unknown keyword 'FLY'\n",
                                b"ERR 12 number: u = nan\n", b"ERR 13 line too long\n"]
            assert got[5] == b"OK START 0\n" and got[6].startswith(b"S 0.000 0.0000 0.0000 ")
            # t on the line is controller time (0.1 s apart), whatever the speed
            ts = [m.t for m in map(p.parse_controller, got[6:]) if isinstance(m, p.Sample)]
            assert ts[:4] == [0.0, 0.1, 0.2, 0.3]
            a.sendall(b"STOP\n")
            assert b"OK STOP\n" in ra.lines(100, until=b"OK STOP\n")
        assert emu.wait_for("disconnect", 120.0)
        assert [e.kind for e in emu.events].count("refused_client") == 1
    finally:
        emu.close()


def test_emulator_cli_serves_and_refuses_bad_options() -> None:
    cmd = [sys.executable, "-m", "peel_bringup.cli", "nachi-emulator"]
    proc = subprocess.Popen([*cmd, "--port", "0", "--speed", "3", "--fault", "no-hello:conn=5"],
                            stdout=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()  # type: ignore[union-attr]
        assert first.startswith("listening on 127.0.0.1:") and "speed 3x" in first
        port = int(first.split(":")[1].split()[0])
        with socket.create_connection(("127.0.0.1", port)) as s:
            assert Reader(s).lines(1) == [b"HELLO NACHI-PEEL 1 EMU-MZ04\n"]
    finally:
        proc.terminate()
        assert proc.wait(timeout=20) == 0
    for bad, text in ((["--speed", "0"], "speed must be a finite number > 0"),
                      (["--fault", "meteor"], "fault kind 'meteor' is not one of"),
                      (["--fault", "drop:when=3"], "is not key=value with a key of"),
                      (["--controller-id", "a b"], "must be one token"),
                      (["--port", "70000"], "argument --port: expected an integer >= 0 and <= "
                                            "65535"),
                      (["--seed", "-1"], "argument --seed: expected an integer >= 0")):
        out = subprocess.run(cmd + bad, capture_output=True, text=True, timeout=60)
        assert out.returncode == 2 and out.stderr.startswith("peel nachi-emulator: error: "), bad
        assert text in out.stderr and "Traceback" not in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr


def test_taken_port_is_a_named_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(PeelError, match=f"cannot listen on 127.0.0.1:{port}"):
            ControllerEmulator(EmulatorOptions(port=port), robot=_NoRobot()).bind()


class _NoRobot:
    dt = 0.1

    def close(self) -> None: ...


def test_fault_specs() -> None:
    f = parse_fault("stall:t=0.6,s=3,task=2")
    assert (f.kind, f.t, f.s, f.task) == ("stall", 0.6, 3.0, 2)
    assert parse_fault("no-hello").conn is None
    for bad in ("spike:f=x", "drop:t=-1", "garbage:n=0", "drop:t"):
        with pytest.raises(PeelError):
            parse_fault(bad)


# ---------------------------------------------------------------------------------- parameters
def test_shipped_parameter_file_is_the_code_defaults() -> None:
    shipped = load_param_file(ROOT / "config" / f"{NODE_NAME}.yaml", NODE_NAME)
    assert shipped == {s.name: s.default for s in BRIDGE_SPECS}
    cfg = load_config()
    assert cfg.link.port == p.DEFAULT_PORT and cfg.safety.f_prewarn_n == 20.0
    assert cfg.safety.stall_timeout_s == 0.3 and cfg.node.task_slot_s == 100.0


@pytest.mark.parametrize(("values", "message"), [
    ({"link.port": 70000}, "'link.port' = 70000 is above its maximum 65535"),
    ({"link.host": ""}, "'link.host' = '' must be a non-empty address"),
    ({"link.backoff_factor": 0.5}, "'link.backoff_factor' = 0.5 is below its minimum 1.0"),
    ({"safety.bad_line_limit": 0}, "'safety.bad_line_limit' = 0 is below its minimum 1"),
    ({"safety.f_prewarn_n": float("nan")}, "'safety.f_prewarn_n' must be finite"),
    ({"node.tasks": 2.5}, "'node.tasks': wrong type, expected INTEGER got DOUBLE"),
    ({"safety.stall_timeout_s": 1}, "'safety.stall_timeout_s': wrong type, expected DOUBLE got "
                                    "INTEGER (1) (write a float, e.g. 1.0)"),
    ({"safety.stall_s": 1.0}, "unknown parameter 'safety.stall_s'"),
])
def test_invalid_parameters_are_named(values: dict[str, object], message: str) -> None:
    with pytest.raises(ParameterError, match=message.replace("(", r"\(").replace(")", r"\)")):
        BridgeConfig.from_params(values)


def test_other_nodes_parameters_and_ros_ones_are_ignored() -> None:
    cfg = BridgeConfig.from_params({"task.q_ter_mm": 6.0, "use_sim_time": True,
                                    "start_type_description_service": True, "link.port": 48110})
    assert cfg.link.port == 48110
