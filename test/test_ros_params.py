"""Parameters as rclpy parameters with descriptors (docs/runtime.md, "Parameters").

In-process: a node declaring specs with :func:`peel_msgs_py.ros.parameters.declare` gets
descriptors (description, ranges, read-only); a wrong-typed, out-of-range, read-only or
disallowed value from ``set_parameters`` is refused with the parameter named and the node keeps
its old value. Real node processes: a YAML file or ``-p`` with a wrong type, an out-of-range
value, an unknown name or a misspelled node section is refused with one line naming it and
exit status 2, before the node does anything.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import ParamSpec
from peel_msgs_py.ros.parameters import NamedRefusals, declare

SPECS = (
    ParamSpec("gain", float, 1.0, "a gain (Eq. 0)", min=0.0, max=10.0, dynamic=True),
    ParamSpec("count", int, 3, "a count", min=1, dynamic=True),
    ParamSpec("mode", str, "a", "a mode", choices=("a", "b"), dynamic=True),
    ParamSpec("fixed", float, 2.0, "not changeable at run time", min=0.0),
)


class _Node(NamedRefusals, Node):
    pass


@pytest.fixture
def node():
    rclpy.init(args=[])
    n = _Node("param_test", start_parameter_services=False)
    yield n
    n.destroy_node()
    rclpy.try_shutdown()


def test_descriptors_ranges_and_read_only(node: Node) -> None:
    assert declare(node, SPECS)["gain"] == 1.0
    (gain, count, mode, fixed) = node.describe_parameters(["gain", "count", "mode", "fixed"])
    assert gain.description == "a gain (Eq. 0)" and not gain.read_only
    assert (gain.floating_point_range[0].from_value, gain.floating_point_range[0].to_value) == (
        0.0, 10.0)
    assert count.integer_range[0].from_value == 1 and count.integer_range[0].to_value == 2**63 - 1
    assert mode.additional_constraints == "one of: a, b"
    assert fixed.read_only and math.isinf(fixed.floating_point_range[0].to_value)


def test_refused_set_parameters_name_the_parameter_and_keep_the_old_value(node: Node) -> None:
    declare(node, SPECS)
    cases = [Parameter("gain", value=2), Parameter("gain", value=12.5),
             Parameter("gain", value=math.inf), Parameter("count", value=0),
             Parameter("mode", value="c"), Parameter("fixed", value=3.0)]
    for param in cases:
        (res,) = node.set_parameters([param])
        assert not res.successful, param.name
        assert param.name in res.reason, res.reason
    assert [node.get_parameter(n).value for n in ("gain", "count", "mode", "fixed")] == [
        1.0, 3, "a", 2.0]
    (res,) = node.set_parameters([Parameter("gain", value=2.5)])
    assert res.successful and node.get_parameter("gain").value == 2.5


def test_overrides_are_checked_at_declaration() -> None:
    rclpy.init(args=["x", "--ros-args", "-p", "gain:=3", "-p", "count:=5"])
    n = _Node("param_test2", start_parameter_services=False)
    try:
        with pytest.raises(ParameterError, match="parameter 'gain': wrong type, expected DOUBLE "
                                                 r"got INTEGER \(3\) \(write a float"):
            declare(n, SPECS)
    finally:
        n.destroy_node()
        rclpy.try_shutdown()


def _node(module: str, *ros_args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", module, "--ros-args", *ros_args],
                          capture_output=True, text=True, timeout=120)


PLANNER_CASES = {
    "mppi:\n      lambda: 1": "parameter 'mppi.lambda': wrong type, expected DOUBLE got INTEGER",
    "mppi:\n      lambda: -0.5": "parameter 'mppi.lambda'",
    "mppi:\n      n_sampels: 50": "unknown parameter 'mppi.n_sampels'",
    "task:\n      q_ter_mm: 25": "parameter 'task.q_ter_mm': wrong type",
}


@pytest.mark.parametrize("body", sorted(PLANNER_CASES))
def test_planner_process_refuses_a_bad_yaml_file(tmp_path: Path, body: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("peel_planner_node:\n  ros__parameters:\n    " + body + "\n")
    res = _node("peel_planner_node.node", "--params-file", str(path))
    assert res.returncode == 2, res.stdout + res.stderr
    (line,) = res.stderr.strip().splitlines()
    assert line.startswith("peel_planner_node: error: ") and PLANNER_CASES[body] in line, line


def test_other_nodes_refuse_unknown_names_sections_and_values(tmp_path: Path) -> None:
    section = tmp_path / "section.yaml"
    section.write_text("peel_sim_nod:\n  ros__parameters:\n    node:\n      tasks: 2\n")
    epocs = tmp_path / "epocs.yaml"
    epocs.write_text("model_learner_node:\n  ros__parameters:\n    train:\n      epocs: 5\n")
    cases = [
        ("peel_sim_node.node", ["--params-file", str(section)], "unknown node section 'peel_sim_nod'"),
        ("peel_sim_node.node", ["-p", "node.cmd_timeout_s:=0.0"], "parameter 'node.cmd_timeout_s'"),
        ("peel_sim_node.node", ["-p", "node.source:=moon"], "parameter 'node.source'"),
        ("model_learner_node.node", ["--params-file", str(epocs)], "unknown parameter 'train.epocs'"),
    ]
    for module, args, expected in cases:
        res = _node(module, *args)
        assert res.returncode == 2, (module, args, res.stderr)
        (line,) = res.stderr.strip().splitlines()
        assert expected in line, line
