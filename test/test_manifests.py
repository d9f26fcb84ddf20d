"""Package manifests a Jazzy machine can install from (README "Installing on Jazzy").

Every third-party module a package imports (anywhere in its sources, the launch file included;
``setup.py`` is the build script and is left out) is declared in its ``package.xml`` under its
rosdep key, so that ``rosdep install --from-paths src`` installs it; a module for which
rosdistro has no key is named in a ``<!-- no rosdep key: DIST ... -->`` comment of the manifest,
pinned in ``requirements.txt`` and listed in the README, and comes from pip.
"""

from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["peel_msgs_py", "peel_model", "peel_bag", "peel_bridge", "peel_sim_node",
            "peel_nachi_bridge", "peel_nachi_emulator", "model_learner_node", "peel_planner_node",
            "peel_residual", "peel_experiments", "peel_bringup"]
#: Top-level module -> rosdep key. ROS modules are ROS packages (the key is the package name, each
#: released in rosdistro's jazzy/distribution.yaml); the python3-* keys are those of rosdistro's
#: rosdep/python.yaml, each with an ubuntu entry (both checked in ros/rosdistro at 8468e88).
ROSDEP_KEYS = {
    **{m: m for m in ("rclpy", "std_msgs", "geometry_msgs", "rosgraph_msgs", "builtin_interfaces",
                      "rcl_interfaces", "std_srvs", "diagnostic_msgs", "lifecycle_msgs", "launch",
                      "launch_ros", "ament_index_python")},
    "numpy": "python3-numpy", "yaml": "python3-yaml", "torch": "python3-torch",
    "pybullet": "python3-pybullet-pip", "rosbags": "python3-rosbags-pip",
    "matplotlib": "python3-matplotlib", "tqdm": "python3-tqdm", "sklearn": "python3-sklearn",
    "scipy": "python3-scipy",
}
#: Top-level module -> pip distribution, for modules rosdistro has no key for.
PIP_ONLY = {"mcap": "mcap", "safetensors": "safetensors", "pyarrow": "pyarrow",
            "pytorch_mppi": "pytorch-mppi", "foxglove": "foxglove-sdk"}


def third_party_imports(pkg: str) -> dict[str, Path]:
    """Top-level modules ``pkg`` imports that are neither the standard library nor ours, with one
    file importing each."""
    found: dict[str, Path] = {}
    for path in sorted((ROOT / "src" / pkg).rglob("*.py")):
        if path.name == "setup.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in (n.split(".")[0] for n in names):
                if name not in sys.stdlib_module_names and name not in PACKAGES:
                    found.setdefault(name, path)
    return found


def manifest(pkg: str) -> tuple[ET.Element, str]:
    path = ROOT / "src" / pkg / "package.xml"
    return ET.parse(path).getroot(), path.read_text()


def runtime_keys(root: ET.Element) -> set[str]:
    return {e.text or "" for tag in ("depend", "exec_depend") for e in root.iter(tag)}


@pytest.mark.parametrize("pkg", PACKAGES)
def test_every_third_party_import_is_declared(pkg: str) -> None:
    root, text = manifest(pkg)
    keys = runtime_keys(root)
    pip_comments = set(re.findall(r"<!-- no rosdep key: (\S+) ", text))
    for module, path in third_party_imports(pkg).items():
        where = f"{path.relative_to(ROOT)} imports {module}"
        if module in PIP_ONLY:
            assert PIP_ONLY[module] in pip_comments, \
                f"{where}: name it in a '<!-- no rosdep key: {PIP_ONLY[module]} ...' comment"
            continue
        assert module in ROSDEP_KEYS, f"{where}: find its rosdep key and add it to ROSDEP_KEYS"
        assert ROSDEP_KEYS[module] in keys, \
            f"{where}: declare <exec_depend>{ROSDEP_KEYS[module]}</exec_depend> in its package.xml"


@pytest.mark.parametrize("pkg", PACKAGES)
def test_declared_keys_are_known(pkg: str) -> None:
    """No typo and no unverified key: each python3-* key is one of ROSDEP_KEYS, each other one
    a ROS module of ROSDEP_KEYS, one of our packages or ros2launch (``ros2 launch``)."""
    root, _ = manifest(pkg)
    known = set(ROSDEP_KEYS.values()) | set(PACKAGES) | {"ros2launch", "python3-pytest"}
    declared = runtime_keys(root) | {e.text or "" for e in root.iter("test_depend")}
    assert declared <= known, f"{pkg}/package.xml declares unknown keys {declared - known}"


def test_pip_only_modules_are_pinned_and_documented() -> None:
    reqs = {line.split("==")[0].lower() for line in (ROOT / "requirements.txt").read_text().splitlines()
            if "==" in line and not line.startswith("#")}
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Installing on Jazzy", 1)[1].split("\n## ", 1)[0]
    for dist in PIP_ONLY.values():
        assert dist in reqs, f"{dist} is not pinned in requirements.txt"
        assert f"`{dist}`" in section, f"README 'Installing on Jazzy' does not name `{dist}`"


def test_license() -> None:
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    for pkg in PACKAGES:
        root, _ = manifest(pkg)
        assert [e.text for e in root.iter("license")] == ["Apache-2.0"], pkg
        assert 'license="Apache-2.0"' in (ROOT / "src" / pkg / "setup.py").read_text(), pkg
