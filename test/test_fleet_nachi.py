"""``peel fleet --plant nachi`` (docs/fleet.md, "Cells on Nachi controllers"): one Nachi
controller per cell.

* without processes: each cell's Nachi bridge gets its own controller (``link.host`` /
  ``link.port``), its producer name, ``node.autostart`` and the override file's section of it,
  under its namespace; ``--cells``
  defaults to the number of controllers; every bad ``--nachi-controllers`` / ``--cells`` /
  ``--plant`` combination is one line and exit 2 before anything starts;
* as real processes on the test's own ROS domain: two ``peel nachi-emulator`` processes and a
  two-cell fleet; both cells finish, both planners get every update, exit 0, and each emulator
  served exactly its own cell (its controller id in that cell's bridge log, its task count).
"""

from __future__ import annotations

import json
import subprocess
import sys
import types
from pathlib import Path
from typing import Any

import pytest
from graph_helpers import ALONE, FAST, node_env, override_yaml

from peel_bringup import fleet
from peel_msgs_py.cliargs import run_main
from peel_msgs_py.errors import PeelError

LEARNER = "/model_learner_node"
NACHI = "peel_nachi_bridge"
RUN_S = 400.0  # only a hang reaches it


def _args(tmp: Path, **kw: object) -> types.SimpleNamespace:
    base = dict(params=None, cells=None, tasks=2, plant="nachi", seed=5, record=None,
                join_after=None, out=str(tmp / "run"), force=False, verbose=False,
                nachi_controllers="127.0.0.1:48101,robot-b:48102")
    return types.SimpleNamespace(**{**base, **kw})


def test_each_cell_drives_its_own_controller_under_its_namespace(tmp_path: Path) -> None:
    run = fleet.resolve(_args(tmp_path))
    assert run.cells == ["/cell_0", "/cell_1"]  # --cells: the number of controllers
    sets = run.settings()
    for c, (cell, (host, port)) in enumerate(zip(run.cells, [("127.0.0.1", 48101),
                                                             ("robot-b", 48102)], strict=True)):
        bridge = sets[cell][NACHI]
        assert (bridge["link.host"], bridge["link.port"]) == (host, port)
        assert bridge["node.learner_node"] == f"{LEARNER}@{cell}" and bridge["node.autostart"]
        assert sets[cell]["peel_planner_node"]["node.autostart"]
        assert set(sets[cell]) == {NACHI, "peel_planner_node"}
        assert run.controller(c) == f"{host}:{port}"
    assert sets[""]["model_learner_node"]["node.cells"] == run.cells
    _, cells = fleet.children_of(run)
    for cell, kids in cells.items():
        assert [k.name for k in kids] == [f"{cell}/peel_planner_node", f"{cell}/{NACHI}"]
        assert kids[1].cmd[2] == f"{NACHI}.node" and kids[1].cmd[-2:] == ["-r", f"__ns:={cell}"]
    assert fleet.resolve(_args(tmp_path, cells=2)).cells == run.cells


def test_the_override_files_bridge_section_reaches_each_namespaced_bridge(tmp_path: Path) -> None:
    """rcl applies a ``peel_nachi_bridge:`` section to the node at the root only: the launcher
    passes its values to each cell's bridge (and planner) as ``-p`` settings."""
    params = tmp_path / "o.yaml"
    params.write_text("peel_nachi_bridge:\n  ros__parameters:\n    safety:\n"
                      "      f_prewarn_n: 15.0\n    link:\n      configure_timeout_s: 1.0\n"
                      "peel_planner_node:\n  ros__parameters:\n    mppi:\n      n_samples: 16\n")
    _, cells = fleet.children_of(fleet.resolve(_args(tmp_path, params=str(params))))
    for kids in cells.values():
        planner, bridge = (" ".join(k.cmd) for k in kids)
        assert "-p safety.f_prewarn_n:=15.0" in bridge, bridge
        assert "-p link.configure_timeout_s:=1.0" in bridge, bridge
        assert "-p mppi.n_samples:=16" in planner and "f_prewarn" not in planner, planner
    assert fleet.file_settings(NACHI, None) == {}  # the shipped file holds the defaults


def test_controllers_parse_ipv6_and_sim_cells_have_none(tmp_path: Path) -> None:
    assert fleet.parse_controllers("[::1]:5, h:7") == [("::1", 5), ("h", 7)]
    assert fleet.controller_name("::1", 5) == "[::1]:5"
    run = fleet.resolve(_args(tmp_path, plant="sim", nachi_controllers=None))
    assert len(run.cells) == fleet.DEFAULT_CELLS and run.controller(0) is None
    assert "peel_sim_node" in run.settings()["/cell_0"]


@pytest.mark.parametrize(("kw", "message"), [
    (dict(plant="sim"), "--nachi-controllers needs --plant nachi"),
    (dict(plant=None), "--nachi-controllers needs --plant nachi"),  # graph.plant: sim
    (dict(nachi_controllers=None), "--plant nachi needs --nachi-controllers"),
    (dict(cells=3), "--cells 3 but 2 controller(s)"),
    (dict(cells=1), "--cells 1 but 2 controller(s)"),
    (dict(nachi_controllers="127.0.0.1"), "'127.0.0.1' is not HOST:PORT"),
    (dict(nachi_controllers="h:1,"), "'' is not HOST:PORT"),
    (dict(nachi_controllers=":48100"), "':48100' is not HOST:PORT"),
    (dict(nachi_controllers="h:port"), "'h:port' is not HOST:PORT"),
    (dict(nachi_controllers="h:-1"), "'h:-1' is not HOST:PORT"),
    (dict(nachi_controllers="::1:48100"), "'::1:48100' is not HOST:PORT"),
    (dict(nachi_controllers="h:0"), "port 0 of 'h:0' is not in 1..65535"),
    (dict(nachi_controllers="h:65536"), "port 65536 of 'h:65536' is not in 1..65535"),
    (dict(nachi_controllers="h:1,H:1"), "H:1 is given twice"),
    (dict(nachi_controllers="a:1,b:2", join_after=1, cells=None), None),  # fine: 2 cells
])
def test_bad_controller_options_are_refused(tmp_path: Path, kw: dict[str, Any],
                                            message: str | None) -> None:
    if message is None:
        assert len(fleet.resolve(_args(tmp_path, **kw)).cells) == 2
        return
    with pytest.raises(PeelError) as err:
        fleet.resolve(_args(tmp_path, **kw))
    assert message in str(err.value) and "\n" not in str(err.value), err.value


def test_bad_input_is_one_line_exit_2_and_nothing_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    for argv in (["--plant", "nachi", "--cells", "3", "--nachi-controllers", "a:1,b:2"],
                 ["--plant", "nachi", "--nachi-controllers", "a:1,a:1"],
                 ["--nachi-controllers", "a:1"]):
        assert run_main("peel fleet", fleet.main, [*argv, "--out", str(out)]) == 2
        (line,) = capsys.readouterr().err.strip().splitlines()
        assert line.startswith("peel fleet: error: --"), line
    assert not out.exists()


OVERRIDE = override_yaml(ALONE, FAST, {
    "model_learner_node": {"node": {"cell_wait_s": 60.0}},
    # eight processes on two cores; the 300 ms rule has its own tests
    "peel_nachi_bridge": {"safety": {"stall_timeout_s": 1.0}},
})


def _emulator(c: int) -> tuple[subprocess.Popen[str], int]:
    """``peel nachi-emulator`` for cell c on a free port, at half real time (its 1 s watchdog
    is 2 s of wall time, as in test_graph_nachi.py), with a controller id of its own."""
    emu = subprocess.Popen([sys.executable, "-m", "peel_bringup.cli", "nachi-emulator",
                            "--port", "0", "--plant", "plant", "--seed", str(4 + c), "--speed",
                            "0.5", "--controller-id", f"EMU-CELL{c}"], env=node_env(),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    first = emu.stdout.readline()  # type: ignore[union-attr]  # "listening on HOST:PORT (...)"
    assert first.startswith("listening on "), first
    return emu, int(first.split(":")[1].split()[0])


def _stop(emus: list[subprocess.Popen[str]]) -> list[str]:
    for emu in emus:
        emu.terminate()
    return [emu.communicate(timeout=30)[0] for emu in emus]


@pytest.mark.process  # starts processes: scripts/flaky.sh
def test_two_cells_on_two_emulated_controllers(tmp_path: Path, ros_domain: str) -> None:
    params = tmp_path / "override.yaml"
    params.write_text(OVERRIDE)
    emus: list[subprocess.Popen[str]] = []
    try:
        ports = [emus.append(e) or p for e, p in (_emulator(c) for c in range(2))]
        cmd = [sys.executable, "-m", "peel_bringup.cli", "fleet", "--cells", "2", "--tasks", "1",
               "--plant", "nachi", "--nachi-controllers",
               ",".join(f"127.0.0.1:{p}" for p in ports), "--params", str(params), "--out",
               str(tmp_path / "run")]
        out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=RUN_S)
    finally:
        emu_logs = _stop(emus)
    text = out.stdout + out.stderr
    assert out.returncode == 0, text
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["plant"] == "nachi" and summary["status"] == 0 and summary["dead"] == []
    updates = {(f"{LEARNER}@{cell}", r["task"]) for cell, c in summary["cells"].items()
               for r in c["results"] if r["update"] and r["update"]["status"] == "swapped"}
    assert updates == {(f"{LEARNER}@/cell_{c}", 1) for c in (0, 1)}, text
    for c, port in enumerate(ports):
        cell = summary["cells"][f"/cell_{c}"]
        assert cell["controller"] == f"127.0.0.1:{port}", cell
        assert [r["task"] for r in cell["results"]] == [1], text
        # planned through the namespaced /cell_<c>/peel/cmd_vel: no watchdog or lost-link abort
        assert cell["results"][0]["outcome"] in ("done", "safety_stop", "timeout"), cell
        assert {(m["producer"], m["task"]) for m in cell["models"]} >= updates, cell["models"]
        log = (tmp_path / "run" / "logs" / f"cell_{c}" / f"{NACHI}.log").read_text()
        assert f"connected to controller EMU-CELL{c} at 127.0.0.1:{port}" in log, log[-2000:]
        assert "Traceback" not in log
        # emulator c served cell c's one task (and no other cell's: each bridge has one link)
        assert "connection 0 from" in emu_logs[c] and emu_logs[c].count(": START") == 1, \
            emu_logs[c]
        assert "Traceback" not in emu_logs[c], emu_logs[c]
