"""Node parameters from ROS 2 parameter YAML files and ``-p``, with rclpy's checks.

Overrides come from ``--ros-args --params-file FILE`` (sections ``/**`` and the node's name)
and ``-p name:=value``; a wrong-typed or out-of-range value is refused naming the parameter;
malformed YAML and unknown ROS arguments give a one-line PeelError. Also: the Parameter
class, local set_parameters with an on-set callback, and the loopback DDS configuration.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ["PEEL_RUNTIME"] = "dds"

from peel_msgs_py.errors import ParameterError, PeelError
from peel_msgs_py.runtime import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    Node,
    Parameter,
    ParameterAlreadyDeclaredException,
    ParameterDescriptor,
    ParameterNotDeclaredException,
    SetParametersResult,
    rclpy,
    remove_ros_args,
)
from peel_msgs_py.runtime.embedded import config
from peel_msgs_py.runtime.msg import FloatingPointRange, IntegerRange

YAML = """\
/**:
  ros__parameters:
    shared: "everyone"
    gain: 0.5
cfg_node:
  ros__parameters:
    gain: {gain}
    mppi:
      samples: {samples}
      sigma: [1.0, 2.0]
other_node:
  ros__parameters:
    gain: 9.0
"""


def _gain_descriptor() -> ParameterDescriptor:
    return ParameterDescriptor(
        floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10.0)]
    )


def _samples_descriptor() -> ParameterDescriptor:
    return ParameterDescriptor(integer_range=[IntegerRange(from_value=1, to_value=4096)])


@pytest.fixture
def ros(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(10 + (os.getpid() * 3 + 11) % 200))
    started = []

    def init(*args: str) -> None:
        rclpy.init(args=["prog", *args])
        started.append(True)

    yield init
    rclpy.try_shutdown()


def _params_file(tmp_path: Path, gain: str = "2.5", samples: str = "256") -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(YAML.format(gain=gain, samples=samples))
    return path


def test_params_file_and_cli_overrides(tmp_path: Path, ros) -> None:
    ros("--ros-args", "--params-file", str(_params_file(tmp_path)), "-p", "mppi.samples:=512")
    node = Node("cfg_node")
    assert node.declare_parameter("gain", 1.0, _gain_descriptor()).value == 2.5  # node section
    assert node.declare_parameter("shared", "").value == "everyone"  # /** section
    assert node.declare_parameter("mppi.samples", 1, _samples_descriptor()).value == 512  # -p
    assert node.declare_parameter("mppi.sigma", [0.0]).value == [1.0, 2.0]
    assert node.declare_parameter("not_in_file", 7).value == 7  # the default
    assert node.get_parameter("use_sim_time").value is False
    assert set(node.get_parameters_by_prefix("mppi")) == {"samples", "sigma"}
    with pytest.raises(ParameterAlreadyDeclaredException, match="'gain'"):
        node.declare_parameter("gain", 1.0)
    with pytest.raises(ParameterNotDeclaredException, match="'nope'"):
        node.get_parameter("nope")
    node.destroy_node()


def test_auto_declared_from_overrides(tmp_path: Path, ros) -> None:
    ros("--ros-args", "--params-file", str(_params_file(tmp_path)))
    node = Node("cfg_node", automatically_declare_parameters_from_overrides=True)
    values = {n: p.value for n, p in node.get_parameters_by_prefix("").items()}
    assert values == {
        "use_sim_time": False,
        "shared": "everyone",
        "gain": 2.5,
        "mppi.samples": 256,
        "mppi.sigma": [1.0, 2.0],
    }
    node.destroy_node()


@pytest.mark.parametrize(
    ("gain", "samples", "exc", "pattern"),
    [
        ("2", "256", InvalidParameterTypeException, r"'gain'.*expected 'DOUBLE' got 'INTEGER'"),
        ('"high"', "256", InvalidParameterTypeException, r"'gain'.*got 'STRING'"),
        ("12.5", "256", InvalidParameterValueException, r"'gain' = 12.5 is out of range"),
        ("2.5", "0", InvalidParameterValueException, r"'mppi.samples' = 0 is out of range"),
        ("2.5", "64.0", InvalidParameterTypeException, r"'mppi.samples'.*expected 'INTEGER'"),
    ],
)
def test_wrong_typed_or_out_of_range_file_value_is_refused(
    tmp_path: Path, ros, gain: str, samples: str, exc: type, pattern: str
) -> None:
    ros("--ros-args", "--params-file", str(_params_file(tmp_path, gain, samples)))
    node = Node("cfg_node")
    with pytest.raises(exc, match=pattern) as info:
        node.declare_parameter("gain", 1.0, _gain_descriptor())
        node.declare_parameter("mppi.samples", 1, _samples_descriptor())
    assert isinstance(info.value, ParameterError) and "\n" not in str(info.value)
    node.destroy_node()


def test_bad_files_and_arguments(tmp_path: Path, ros) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("cfg_node:\n  ros__parameters:\n    gain: [1.0, 2.0\n")
    ros("--ros-args", "--params-file", str(bad))
    with pytest.raises(PeelError, match=r"malformed YAML in parameter file .*bad.yaml at line"):
        Node("cfg_node")
    rclpy.try_shutdown()
    mixed = tmp_path / "mixed.yaml"
    mixed.write_text("cfg_node:\n  ros__parameters:\n    sigma: [1.0, two]\n")
    ros("--ros-args", "--params-file", str(mixed))
    with pytest.raises(ParameterError, match="'sigma'"):
        Node("cfg_node")
    rclpy.try_shutdown()
    with pytest.raises(PeelError, match="no such file"):
        rclpy.init(args=["--ros-args", "--params-file", str(tmp_path / "missing.yaml")])
    with pytest.raises(PeelError, match="unknown ROS argument '--bogus'"):
        rclpy.init(args=["--ros-args", "--bogus"])
    assert remove_ros_args(["prog", "--x", "--ros-args", "-p", "a:=1", "--", "y"]) == [
        "prog",
        "--x",
        "y",
    ]


def test_local_set_parameters_and_callbacks(ros) -> None:
    ros()
    node = Node("cfg_node", namespace="/lab")
    assert node.get_fully_qualified_name() == "/lab/cfg_node"
    node.declare_parameter("gain", 1.0, _gain_descriptor())
    node.declare_parameter("frozen", "x", ParameterDescriptor(read_only=True))
    seen = []
    node.add_post_set_parameters_callback(lambda ps: seen.extend(p.name for p in ps))

    def veto(params: list[Parameter]) -> SetParametersResult:
        if any(p.name == "gain" and p.value == 3.0 for p in params):
            return SetParametersResult(successful=False, reason="3.0 is unlucky")
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(veto)
    results = node.set_parameters(
        [
            Parameter("gain", value=4.0),
            Parameter("gain", value=3.0),
            Parameter("gain", value=4),
            Parameter("frozen", value="y"),
        ]
    )
    assert [r.successful for r in results] == [True, False, False, False]
    assert results[1].reason == "3.0 is unlucky"
    assert "'gain'" in results[2].reason
    assert results[3].reason == "parameter 'frozen' is read-only"
    assert node.get_parameter("gain").value == 4.0 and seen == ["gain"]
    with pytest.raises(ParameterNotDeclaredException):
        node.set_parameters([Parameter("nope", value=1.0)])
    node.destroy_node()


def test_parameter_class_round_trips_messages() -> None:
    for value in (True, 3, 2.5, "s", [True, False], [1, 2], [1.5], ["a", "b"]):
        p = Parameter("x", value=value)
        back = Parameter.from_parameter_msg(p.to_parameter_msg())
        assert back == p and back.type_ is p.type_
    assert Parameter("x", value=2.5).type_ is Parameter.Type.DOUBLE
    with pytest.raises(ValueError):
        Parameter("x", Parameter.Type.DOUBLE, 3)
    with pytest.raises(TypeError):
        Parameter("x", value=[1, "a"])


def test_loopback_config_is_the_default(monkeypatch: pytest.MonkeyPatch) -> None:
    env = {"ROS_DOMAIN_ID": "42"}
    xml = config.domain_config(env)
    assert xml is not None
    assert '<NetworkInterface address="127.0.0.1"/>' in xml
    assert "<AllowMulticast>false</AllowMulticast>" in xml
    assert '<Peer address="127.0.0.1"/>' in xml
    assert "<ParticipantIndex>auto</ParticipantIndex>" in xml
    assert config.domain_id(env) == 42
    assert config.domain_config({"PEEL_DDS_NETWORK": "1"}) is None
    assert config.network_mode({"CYCLONEDDS_URI": "file:///etc/cdds.xml"}) == "user"
    with pytest.raises(PeelError, match=r"ROS_DOMAIN_ID must lie in 0\.\.232"):
        config.domain_id({"ROS_DOMAIN_ID": "300"})
    with pytest.raises(PeelError, match="ROS_DOMAIN_ID must be an integer"):
        config.domain_id({"ROS_DOMAIN_ID": "x"})
    with pytest.raises(PeelError, match="PEEL_DDS_NETWORK"):
        config.network_mode({"PEEL_DDS_NETWORK": "maybe"})
