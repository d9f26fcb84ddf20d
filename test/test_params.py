"""peel_msgs_py.params: groups of a flat ROS 2 parameter dict, types as rclpy checks them, and
unknown sections and names refused by every node and command that reads a parameter file."""

import subprocess
import sys

import pytest

from peel_msgs_py.errors import ParameterError, PeelError
from peel_msgs_py.params import (
    ParamSpec,
    load_param_file,
    node_specs,
    registered_nodes,
    ros_args_overrides,
    ros_type_name,
    validate_group,
)

SPECS = [ParamSpec("train.lr", float, 1e-4, min=0.0), ParamSpec("train.epochs", int, 60, min=1)]


def test_group_is_validated_other_groups_ignored_and_prefix_stripped() -> None:
    flat = {"train.lr": 1e-3, "model.h": 10, "trainer.x": "not mine"}
    assert validate_group(SPECS, flat, "train") == {"train.lr": 1e-3, "train.epochs": 60}
    assert validate_group(SPECS, flat, "train", strip=True) == {"lr": 1e-3, "epochs": 60}


def test_bad_value_in_the_group_names_the_parameter() -> None:
    with pytest.raises(ParameterError, match=r"'train\.epochs'"):
        validate_group(SPECS, {"train.epochs": 0}, "train")
    with pytest.raises(ParameterError, match=r"unknown parameter 'train\.lrr'"):
        validate_group(SPECS, {"train.lrr": 1.0}, "train")


def test_types_as_rclpy_checks_them() -> None:
    """No integer for a DOUBLE (rclpy refuses ``mppi.lambda: 1``), no bool for an INTEGER, one
    element type per list; the message is the one the nodes print for the same refusal."""
    lam = ParamSpec("mppi.lambda", float, 0.1, min=1e-9)
    with pytest.raises(ParameterError, match=r"^parameter 'mppi\.lambda': wrong type, expected "
                                             r"DOUBLE got INTEGER \(1\) \(write a float"):
        lam.check(1)
    assert lam.check(1.0) == 1.0
    with pytest.raises(ParameterError, match="expected INTEGER got BOOL"):
        ParamSpec("n", int, 3).check(True)
    with pytest.raises(ParameterError, match="expected DOUBLE_ARRAY got INTEGER_ARRAY"):
        ParamSpec("l", list, [0.1, 0.2]).check([1, 2])
    assert ros_type_name([1.0, 2.0]) == "DOUBLE_ARRAY" and ros_type_name([1, 2.0]) == "MIXED_ARRAY"


def test_every_package_registers_its_node_parameters() -> None:
    assert set(registered_nodes()) >= {"peel_sim_node", "peel_planner_node",
                                       "model_learner_node", "peel_bringup"}
    names = {s.name for s in node_specs("peel_planner_node")}
    assert {"mppi.lambda", "model.path", "node.seed", "use_sim_time"} <= names
    assert node_specs("no_such_node") is None


def _write(tmp_path, text: str):
    path = tmp_path / "p.yaml"
    path.write_text(text)
    return path


def test_unknown_sections_and_names_are_refused(tmp_path) -> None:
    cases = {
        "peel_planner_node:\n  ros__parameters:\n    mppi:\n      n_sampels: 50\n":
            r"unknown parameter 'mppi\.n_sampels' for peel_planner_node",
        "peel_planer_node:\n  ros__parameters:\n    mppi:\n      lambda: 0.2\n":
            r"unknown node section 'peel_planer_node'",
        "/**:\n  ros__parameters:\n    task:\n      q_ter_mmm: 25.0\n":
            r"unknown parameter 'task\.q_ter_mmm' under /\*\*",
    }
    for text, pattern in cases.items():
        with pytest.raises(ParameterError, match=pattern):
            load_param_file(_write(tmp_path, text), "peel_planner_node")
    # a /** name one node declares is fine for every node; other nodes' sections too
    ok = _write(tmp_path, "/**:\n  ros__parameters:\n    task:\n      q_ter_mm: 6.0\n"
                          "model_learner_node:\n  ros__parameters:\n    maml:\n      m: 2\n")
    assert load_param_file(ok, "peel_planner_node") == {"task.q_ter_mm": 6.0}
    assert load_param_file(ok, "model_learner_node") == {"task.q_ter_mm": 6.0, "maml.m": 2}


def test_not_utf8_file_is_one_line_error(tmp_path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes("peel_sim_node:\n  ros__parameters:\n    x: 'Größe'\n".encode("latin-1"))
    with pytest.raises(PeelError, match="not valid UTF-8"):
        load_param_file(path, "peel_sim_node")


def test_ros_args_are_checked_by_name(tmp_path) -> None:
    good = _write(tmp_path, "peel_planner_node:\n  ros__parameters:\n    mppi:\n      lambda: 0.2\n")
    got = ros_args_overrides(["prog", "--ros-args", "--params-file", str(good), "-p",
                              "mppi.horizon:=4", "-p", "other_node:whatever:=1"],
                             "peel_planner_node")
    assert got == {"mppi.lambda": 0.2, "mppi.horizon": 4}
    with pytest.raises(ParameterError, match=r"unknown parameter 'mppi\.n_sampels'"):
        ros_args_overrides(["prog", "--ros-args", "-p", "mppi.n_sampels:=5"], "peel_planner_node")


def test_every_command_taking_a_parameter_file_refuses_unknown_names(tmp_path) -> None:
    ep = _write(tmp_path, "model_learner_node:\n  ros__parameters:\n    train:\n      epocs: 5\n")
    sim = tmp_path / "sim.yaml"
    sim.write_text("peel_sim_node:\n  ros__parameters:\n    scene:\n      bogus: 1.0\n")
    exp = tmp_path / "exp.yaml"
    exp.write_text("peel_bringup:\n  ros__parameters:\n    experiment:\n      taskz: 3\n")
    commands = [
        (["train", "--params-file", str(ep), "--data", str(tmp_path / "d"), "--out",
          str(tmp_path / "ck.safetensors")], "unknown parameter 'train.epocs'"),
        (["figures", "--params-file", str(ep), "--data", str(tmp_path / "d"), "--out",
          str(tmp_path / "fig")], "unknown parameter 'train.epocs'"),
        (["dataset", "--params-file", str(sim), "--param-sets", "1", "--per-set", "1", "--out",
          str(tmp_path / "ds")], "unknown parameter 'scene.bogus'"),
        (["experiment", "--params-file", str(exp), "--tasks", "1", "--out",
          str(tmp_path / "ex")], "unknown parameter 'experiment.taskz'"),
        (["graph", "--params", str(exp), "--out", str(tmp_path / "g")],
         "unknown parameter 'experiment.taskz'"),
        (["demo", "--params", str(ep), "--out", str(tmp_path / "demo")],
         "unknown parameter 'train.epocs'"),
    ]
    for argv, expected in commands:
        res = subprocess.run([sys.executable, "-m", "peel_bringup.cli", *argv],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 2, (argv, res.stdout, res.stderr)
        (line,) = res.stderr.strip().splitlines()
        assert expected in line, (argv, line)
        assert not (tmp_path / "ds").exists() and not (tmp_path / "g").exists()


def test_an_experiment_override_file_for_another_node_is_refused_with_the_right_flag(tmp_path) -> None:
    """Each of peel experiment's override flags reads one node's section; a file written for
    another node would pass unread, so it is refused, naming the section and its flag."""
    planner = tmp_path / "planner.yaml"
    planner.write_text("peel_planner_node:\n  ros__parameters:\n    safety:\n      slowdown:\n"
                       "        enabled: true\n")
    bringup = tmp_path / "bringup.yaml"
    bringup.write_text("peel_bringup:\n  ros__parameters:\n    experiment:\n      tasks: 3\n")
    cases = [
        (["experiment", "--params-file", str(planner)], "section 'peel_planner_node'",
         "--planner-params"),
        (["experiment", "grid", "--seeds", "0", "--params-file", str(planner)], "section 'peel_planner_node'",
         "--planner-params"),
        (["experiment", "--planner-params", str(bringup)], "section 'peel_bringup'",
         "--params-file"),
        (["experiment", "--sim-params", str(planner)], "section 'peel_planner_node'",
         "--planner-params"),
    ]
    for argv, section, flag in cases:
        out = tmp_path / "ex"
        res = subprocess.run([sys.executable, "-m", "peel_bringup.cli", *argv, "--tasks", "1",
                              "--out", str(out)], capture_output=True, text=True, timeout=120)
        assert res.returncode == 2, (argv, res.stdout, res.stderr)
        (line,) = res.stderr.strip().splitlines()
        assert section in line and f"pass it with {flag}" in line, (argv, line)
        assert not out.exists()
