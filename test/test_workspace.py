"""The workspace itself: ament_python packages, the `peel` command, one-way dependencies."""

from __future__ import annotations

import ast
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["peel_msgs_py", "peel_bridge", "peel_sim_node", "peel_nachi_bridge", "model_learner_node",
            "peel_planner_node", "peel_bringup"]
#: Allowed imports between our packages (the dependency direction of docs/CONTRACT.md).
ALLOWED = {
    "peel_msgs_py": set(),
    "peel_bridge": {"peel_msgs_py"},
    "peel_sim_node": {"peel_msgs_py", "peel_bridge"},
    "peel_nachi_bridge": {"peel_msgs_py", "peel_bridge", "peel_sim_node"},  # the emulator's plant
    "model_learner_node": {"peel_msgs_py", "peel_sim_node"},  # dataset reader (peel train)
    "peel_planner_node": {"peel_msgs_py", "model_learner_node"},
    "peel_bringup": set(PACKAGES) - {"peel_bringup"},
}
ROS_MODULES = {"rclpy", "geometry_msgs", "std_msgs", "rosgraph_msgs", "rcl_interfaces",
               "builtin_interfaces", "std_srvs", "diagnostic_msgs", "launch", "launch_ros",
               "ament_index_python"}


@pytest.mark.parametrize("pkg", PACKAGES)
def test_package_is_ament_python(pkg: str) -> None:
    base = ROOT / "src" / pkg
    root = ET.parse(base / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == pkg
    assert root.find("export/build_type").text == "ament_python"
    assert (base / "resource" / pkg).is_file()
    assert (base / "setup.cfg").is_file()
    assert (base / pkg / "__init__.py").is_file()
    setup = (base / "setup.py").read_text()
    assert f'package_name = "{pkg}"' in setup


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("pkg", PACKAGES)
def test_dependencies_point_one_way(pkg: str) -> None:
    for path in (ROOT / "src" / pkg / pkg).rglob("*.py"):
        ours = _imports(path) & set(PACKAGES)
        bad = ours - ALLOWED[pkg] - {pkg}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad} against the dependency direction"


def test_libraries_import_no_ros() -> None:
    """Only node modules (``*node.py``) and ``peel_msgs_py.ros`` may touch ROS modules."""
    for pkg in PACKAGES:
        for path in (ROOT / "src" / pkg / pkg).rglob("*.py"):
            rel = path.relative_to(ROOT / "src" / pkg / pkg)
            if (pkg, rel.parts[0]) == ("peel_msgs_py", "ros") or path.name.endswith("node.py"):
                continue
            bad = _imports(path) & ROS_MODULES
            assert not bad, f"library module {path.relative_to(ROOT)} imports ROS: {bad}"


def _peel(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", *args],
                          capture_output=True, text=True, timeout=120)


def test_peel_help_lists_subcommands() -> None:
    out = _peel("--help")
    assert out.returncode == 0
    for name in ("dataset", "train", "bench", "experiment", "graph", "demo", "nachi-emulator"):
        assert f"  {name}" in out.stdout


def test_unknown_command_is_one_line_error() -> None:
    out = _peel("frobnicate")
    assert out.returncode == 2
    assert out.stderr.startswith("peel: error: unknown command 'frobnicate'")
    assert "Traceback" not in out.stderr


def test_unknown_bench_target_is_one_line_error() -> None:
    out = _peel("bench", "warp-drive")
    assert out.returncode == 2
    assert "unknown benchmark 'warp-drive'" in out.stderr
    assert "Traceback" not in out.stderr


def test_the_embedded_runtime_is_retired() -> None:
    """rclpy is the one runtime: no module, test, requirement or setup step names the embedded
    Cyclone DDS runtime any more."""
    assert not (ROOT / "src" / "peel_msgs_py" / "peel_msgs_py" / "runtime").exists()
    retired = ("peel_msgs_py.runtime", "PEEL_RUNTIME", "cyclonedds")
    files = [*(ROOT / "src").rglob("*.py"), *(ROOT / "test").glob("*.py"),
             *ROOT.glob("requirements*.txt"), ROOT / "scripts" / "setup.sh"]
    for path in files:
        if path.name == Path(__file__).name:
            continue
        text = path.read_text()
        for word in retired:
            assert word not in text, f"{path.relative_to(ROOT)} names {word}"
    reqs = (ROOT / "requirements-ros.txt").read_text()
    for pin in ("ros-rclpy==7.1.6", "ros-rcl-interfaces==2.0.3", "ros-geometry-msgs==5.3.6",
                "ros-std-msgs==5.3.6", "ros-std-srvs==5.3.6", "ros-rosgraph-msgs==2.0.3",
                "ros-rmw-fastrtps-cpp==8.4.3"):
        assert pin in reqs.splitlines(), pin
    assert all(line.startswith("#") or "==" in line for line in reqs.splitlines() if line)
