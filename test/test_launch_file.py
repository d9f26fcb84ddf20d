"""The Jazzy launch file, tested without ``launch``/``launch_ros`` (not available as wheels):
it is run against stand-ins of the launch API that record what it builds, and every executable,
node name and parameter file it names must exist in the packages (docs/graph.md); the managed
nodes start unconfigured for the lifecycle manager (``peel lifecycle up``), whose failure alone
ends the launch, and ``live:=PORT`` adds the live view (``peel live``)."""

from __future__ import annotations

import ast
import importlib.util
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / "src" / "peel_bringup" / "launch" / "peel_graph.launch.py"


class _Action:
    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


def _stand_ins(share: Path) -> dict[str, types.ModuleType]:
    mods = {name: types.ModuleType(name) for name in (
        "launch", "launch.actions", "launch.event_handlers", "launch.events", "launch_ros",
        "launch_ros.actions", "ament_index_python", "ament_index_python.packages")}
    mods["launch"].LaunchDescription = _Action
    for name in ("DeclareLaunchArgument", "EmitEvent", "OpaqueFunction", "RegisterEventHandler",
                 "ExecuteProcess"):
        setattr(mods["launch.actions"], name, type(name, (_Action,), {}))
    mods["launch.event_handlers"].OnProcessExit = type("OnProcessExit", (_Action,), {})
    mods["launch.events"].Shutdown = type("Shutdown", (_Action,), {})
    mods["launch_ros.actions"].Node = type("Node", (_Action,), {})
    mods["ament_index_python.packages"].get_package_share_directory = lambda pkg: str(share / pkg)
    return mods


def _console_scripts(pkg: str) -> dict[str, str]:
    """``name -> module:function`` of a package's setup.py console_scripts."""
    tree = ast.parse((ROOT / "src" / pkg / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if isinstance(key, ast.Constant) and key.value == "console_scripts":
                    return dict(e.value.replace(" ", "").split("=") for e in value.elts)
    return {}


def _actions(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, **given: str) -> tuple[
        dict[str, str], list]:
    """The declared arguments (name -> default) and the actions the launch file builds for
    ``given`` launch arguments."""
    share = tmp_path / "share"
    (share / "peel_bringup").mkdir(parents=True)
    (share / "peel_bringup" / "config").symlink_to(ROOT / "config")
    for name, mod in _stand_ins(share).items():
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location("peel_graph_launch", LAUNCH)
    launch = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(launch)
    desc = launch.generate_launch_description()
    declared = {a.args[0]: a.kwargs.get("default_value") for a in desc.args[0]
                if type(a).__name__ == "DeclareLaunchArgument"}
    (opaque,) = [a for a in desc.args[0] if type(a).__name__ == "OpaqueFunction"]
    context = types.SimpleNamespace(launch_configurations={**declared, **given})
    return declared, opaque.kwargs["function"](context)


@pytest.mark.parametrize(("record", "plant", "live", "namespace"), [
    ("", "sim", "", ""), ("/tmp/bag", "plant", "", ""), ("/tmp/bag", "nachi", "", ""),
    ("", "sim", "8771", ""), ("", "sim", "", "/cell_a")])
def test_launch_file_names_existing_executables_nodes_and_files(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, record: str, plant: str,
        live: str, namespace: str) -> None:
    given = {"record": record, "plant": plant, "live": live, "namespace": namespace}
    if plant == "nachi":
        given.update(nachi_host="10.0.0.5", nachi_port="48113")
    declared, actions = _actions(tmp_path, monkeypatch, **given)
    assert set(declared) == {"plant", "tasks", "seed", "params", "record", "out", "nachi_host",
                             "nachi_port", "live", "live_host", "namespace"}
    assert (declared["live"], declared["live_host"]) == ("", "127.0.0.1")
    nodes = [a for a in actions if type(a).__name__ == "Node"]
    names = {n.kwargs["name"] for n in nodes}
    bridge = "peel_nachi_bridge" if plant == "nachi" else "peel_sim_node"
    tools = {"peel_lifecycle_manager"} | ({"peel_recorder"} if record else set()) | (
        {"peel_live"} if live else set())
    assert names == {bridge, "peel_planner_node", "model_learner_node"} | tools

    from peel_msgs_py.params import load_param_file, registered_nodes

    for node in nodes:
        pkg, exe, name = node.kwargs["package"], node.kwargs["executable"], node.kwargs["name"]
        target = _console_scripts(pkg)[exe]  # the executable exists ...
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func))  # ... and imports
        if name == "peel_recorder":
            assert node.kwargs["arguments"] == ["--out", record]
            continue
        if name == "peel_lifecycle_manager":  # planner first, the bridge last
            ns = f"{namespace}/" if namespace else ""
            assert node.kwargs["arguments"] == ["lifecycle", "up", f"{ns}peel_planner_node",
                                                f"{ns}{bridge}"]
            continue
        if name == "peel_live":
            assert node.kwargs["arguments"] == ["live", "--port", live, "--host", "127.0.0.1"]
            continue
        assert node.kwargs["namespace"] == (namespace or None)  # the whole cell moves
        assert name in registered_nodes()  # a node whose parameters are registered
        files = [p for p in node.kwargs["parameters"] if isinstance(p, str)]
        assert files and all(Path(f).is_file() for f in files)
        for f in files:  # the shipped file loads, names checked
            load_param_file(f, name)
        overrides = next(p for p in node.kwargs["parameters"] if isinstance(p, dict))
        assert overrides["use_sim_time"] is True
        if name == bridge:  # the state's publisher runs the K tasks and ends the launch
            assert overrides["node.tasks"] == 3 and overrides["node.exit_when_done"] is True
        readers = 1 + bool(record) + bool(live)  # the recorder and the live view count
        if name == bridge:
            assert overrides["node.min_subscribers"] == readers
            assert overrides["node.learner_node"] == f"{namespace}/model_learner_node"
        if name == "peel_planner_node":
            assert overrides["node.min_cmd_subscribers"] == readers
        # the managed nodes wait unconfigured for the manager
        assert overrides.get("node.autostart") is (False if name in (bridge, "peel_planner_node")
                                                   else None)
        if name == "peel_nachi_bridge":
            assert (overrides["link.host"], overrides["link.port"]) == ("10.0.0.5", 48113)
        known = {s.name for s in importlib.import_module(f"{name}.parameters").SPECS}
        assert set(overrides) <= known, set(overrides) - known
    handlers = [a for a in actions if type(a).__name__ == "RegisterEventHandler"]
    assert len(handlers) == 4  # any node's exit ends the launch, and the manager's failure


def test_the_managers_failure_ends_the_launch_and_its_arguments_parse(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The manager's exit handler shuts the launch down on a non-zero status only; the
    arguments given to ``peel lifecycle`` and ``peel live`` (with the ROS arguments launch
    appends) parse as those commands parse them."""
    _, actions = _actions(tmp_path, monkeypatch, live="8772", live_host="127.0.0.2")
    nodes = {a.kwargs["name"]: a for a in actions if type(a).__name__ == "Node"}
    manager = nodes["peel_lifecycle_manager"]
    (handler,) = [a.args[0] for a in actions if type(a).__name__ == "RegisterEventHandler"
                  and a.args[0].kwargs["target_action"] is manager]
    on_exit = handler.kwargs["on_exit"]
    assert on_exit(types.SimpleNamespace(returncode=0), None) == []
    (emit,) = on_exit(types.SimpleNamespace(returncode=1), None)
    assert type(emit.kwargs["event"]).__name__ == "Shutdown"

    from rclpy.utilities import remove_ros_args

    from peel_bringup import cli, lifecycle_cli, live_node

    ros = ["--ros-args", "-r", "__node:=x"]
    for node, parser in ((manager, lifecycle_cli._parser()), (nodes["peel_live"],
                                                             live_node._parser())):
        command, *rest = node.kwargs["arguments"]
        assert command in cli.SUBCOMMANDS
        parsed = parser.parse_args(remove_ros_args(["peel", *rest, *ros])[1:])
        if command == "live":
            assert (parsed.port, parsed.host) == (8772, "127.0.0.2")
        else:
            assert (parsed.action, parsed.nodes) == ("up", ["peel_planner_node", "peel_sim_node"])
