"""``colcon build`` of the workspace, as on a Jazzy machine (colcon-core and colcon-ros from the
package index, ``requirements-dev.txt``): every package under ``src/`` builds, installs its
manifest and its executables, and the installed ``peel_bringup`` share folder holds the
parameter files and the Foxglove layout."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent.name for p in (ROOT / "src").glob("*/package.xml"))
EXECUTABLES = {"peel_sim_node": "peel_sim_node", "peel_planner_node": "peel_planner_node",
               "model_learner_node": "model_learner_node", "peel_nachi_bridge": "peel_nachi_bridge",
               "peel_bag": "peel_recorder", "peel_bringup": "peel"}


def test_colcon_builds_every_package_and_installs_the_config(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    ignore = shutil.ignore_patterns("*.egg-info", "__pycache__", "build", "install", "log")
    shutil.copytree(ROOT / "src", ws / "src", symlinks=True, ignore=ignore)
    shutil.copytree(ROOT / "config", ws / "config", ignore=ignore)
    out = subprocess.run([sys.executable, "-m", "colcon", "build", "--base-paths", "src"],
                         cwd=ws, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    install = ws / "install"
    assert sorted(p.name for p in install.iterdir() if p.is_dir()) == PACKAGES
    for pkg in PACKAGES:
        assert (install / pkg / "share" / pkg / "package.xml").is_file(), pkg
    for pkg, exe in EXECUTABLES.items():
        assert (install / pkg / "lib" / pkg / exe).is_file(), (pkg, exe)
    share = install / "peel_bringup" / "share" / "peel_bringup"
    installed = sorted(p.name for p in (share / "config").glob("*.yaml"))
    assert installed == sorted(p.name for p in (ROOT / "config").glob("*.yaml"))
    assert (share / "config" / "foxglove" / "peel_layout.json").is_file()
    assert (share / "launch" / "peel_graph.launch.py").is_file()
