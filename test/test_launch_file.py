"""The Jazzy launch file, tested without ``launch``/``launch_ros`` (not available as wheels):
it is run against stand-ins of the launch API that record what it builds, and every executable,
node name and parameter file it names must exist in the packages (docs/graph.md)."""

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


@pytest.mark.parametrize(("record", "plant", "namespace"), [
    ("", "sim", ""), ("/tmp/bag", "plant", ""), ("/tmp/bag", "nachi", ""), ("", "sim", "/cell_a")])
def test_launch_file_names_existing_executables_nodes_and_files(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, record: str, plant: str,
        namespace: str) -> None:
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
    assert set(declared) == {"plant", "tasks", "seed", "params", "record", "out", "nachi_host",
                             "nachi_port", "namespace"}
    (opaque,) = [a for a in desc.args[0] if type(a).__name__ == "OpaqueFunction"]
    given = {"record": record, "plant": plant, "namespace": namespace}
    if plant == "nachi":
        given.update(nachi_host="10.0.0.5", nachi_port="48113")
    context = types.SimpleNamespace(launch_configurations={**declared, **given})
    actions = opaque.kwargs["function"](context)
    nodes = [a for a in actions if type(a).__name__ == "Node"]
    names = {n.kwargs["name"] for n in nodes}
    bridge = "peel_nachi_bridge" if plant == "nachi" else "peel_sim_node"
    assert names == {bridge, "peel_planner_node", "model_learner_node"} | (
        {"peel_recorder"} if record else set())

    from peel_msgs_py.params import load_param_file, registered_nodes

    for node in nodes:
        pkg, exe, name = node.kwargs["package"], node.kwargs["executable"], node.kwargs["name"]
        target = _console_scripts(pkg)[exe]  # the executable exists ...
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func))  # ... and imports
        if name == "peel_recorder":
            assert node.kwargs["arguments"] == ["--out", record]
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
            assert overrides["node.learner_node"] == f"{namespace}/model_learner_node"
        if name == "peel_nachi_bridge":
            assert (overrides["link.host"], overrides["link.port"]) == ("10.0.0.5", 48113)
        known = {s.name for s in importlib.import_module(f"{name}.parameters").SPECS}
        assert set(overrides) <= known, set(overrides) - known
    handlers = [a for a in actions if type(a).__name__ == "RegisterEventHandler"]
    assert len(handlers) == 3  # any node's exit ends the launch
