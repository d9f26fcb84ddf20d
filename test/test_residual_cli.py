"""``peel residual`` as a real process on real bags (docs/residual.md).

Plant data with effects the tool is not told about (``peel_sim_node.example_effects``), made
in-process with PeelEnv under exploratory command profiles, written with the project's
BagWriter; the command runs in a subprocess; report.json is read with ``json``, the figures
with matplotlib's PNG reader, the corrected checkpoint with the project's loader.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import matplotlib.image as mpimg
import pytest
from residual_helpers import generate_tasks, peel, write_bag

from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_model.compensated import CompensatedPredictor
from peel_msgs_py.cliargs import run_main
from peel_msgs_py.outputs import OutputDir
from peel_residual.cli import main as residual_main
from peel_sim_node.example_effects import slipping_axis, vacuum_leak

REPORT_KEYS = {"rmse_before", "rmse_after", "effects", "unexplained", "holdout"}
EFFECT_KEYS = {"name", "channel", "expression", "coefficients", "explained_variance"}


def _run(tmp: Path, bag: Path, *extra: str) -> dict:
    out = tmp / "out"
    proc = peel("residual", str(bag), "--out", str(out), "--no-progress", *extra)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rep = json.loads((out / "report.json").read_text())
    assert set(rep) >= REPORT_KEYS
    for ch in ("fx", "fz", "v"):
        for mode in ("one_step", "open_loop"):
            assert rep["rmse_before"][ch][mode] > 0 and rep["rmse_after"][ch][mode] > 0
    assert rep["holdout"]["tasks"] and not {t["index"] for t in rep["holdout"]["tasks"]} & {
        t["index"] for t in rep["holdout"]["fit_tasks"]}
    for e in rep["effects"]:
        assert set(e) >= EFFECT_KEYS
        assert e["fit"] in ("one_step", "open_loop")
        assert mpimg.imread(out / e["figure"]).ndim == 3
    assert mpimg.imread(out / "rmse.png").ndim == 3
    assert "## Error before and after" in (out / "report.md").read_text()
    assert json.loads(proc.stdout)["out"] == str(out)
    return rep


def _named(rep: dict) -> set[tuple[str, str]]:
    return {(e["name"], e["channel"]) for e in rep["effects"]}


def test_one_undeclared_effect_is_named_and_the_open_loop_error_falls(tmp_path: Path) -> None:
    """A vacuum leak (load growing in time) on the plant: a drift-in-time term on F_RZ, and
    held-out open-loop RMSE of F_RZ below 0.7 x before."""
    bag = write_bag(tmp_path / "leak", generate_tasks("plant", [vacuum_leak], n=24, seed=11))
    rep = _run(tmp_path, bag)
    assert ("drift_in_time", "fz") in _named(rep), rep["effects"]
    before, after = (rep[k]["fz"]["open_loop"] for k in ("rmse_before", "rmse_after"))
    assert after < 0.7 * before, (before, after)
    model = load_checkpoint(tmp_path / "out" / "corrected.safetensors")
    assert isinstance(model, CompensatedPredictor)
    assert ("drift_in_time", "fz") in {(t.candidate.family, t.channel) for t in model.terms}


def test_two_undeclared_effects_are_both_named(tmp_path: Path) -> None:
    """A slipping axis (75 % of the command) and the vacuum leak at once, in a bag that has only
    the state streams (a robot bridge without /peel/trajectory)."""
    trajs = generate_tasks("plant", [slipping_axis, vacuum_leak], n=24, seed=12)
    bag = write_bag(tmp_path / "two", trajs, trajectory=False, streams=True)
    rep = _run(tmp_path, bag)
    named = _named(rep)
    assert ("speed_scale", "v") in named and ("drift_in_time", "fz") in named, rep["effects"]
    scale = next(e for e in rep["effects"] if e["name"] == "speed_scale")
    assert scale["coefficients"][0] < 0  # slower than commanded


def test_simulator_data_with_the_simulator_model_claims_nothing(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "sim", generate_tasks("sim", n=24, seed=13))
    rep = _run(tmp_path, bag, "--model", str(shipped_checkpoint()))
    assert rep["effects"] == [] and rep["no_effect_claimed"]
    assert rep["corrected_model"] is None
    assert not (tmp_path / "out" / "corrected.safetensors").exists()
    assert "No effect is claimed" in (tmp_path / "out" / "report.md").read_text()
    assert rep["rmse_after"] == rep["rmse_before"]


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_bag(tmp_path_factory.mktemp("bag") / "b", generate_tasks("sim", n=5, seed=1))


def _one_line_error(proc, needle: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], proc.stderr


def test_bag_without_the_needed_topics(tmp_path: Path) -> None:
    import ros_msgs as M

    from peel_bag.bag import BagWriter
    from peel_msgs_py import topics as T

    with BagWriter(tmp_path / "clock") as bag:
        bag.add_topic(T.CLOCK, T.topic(T.CLOCK).type, [T.topic(T.CLOCK).qos])
        bag.write(T.CLOCK, M.serialize(M.Clock()), 1_700_000_000_000_000_000)
    proc = peel("residual", str(tmp_path / "clock"), "--out", str(tmp_path / "o"))
    _one_line_error(proc, "has neither /peel/trajectory nor all of")
    assert not (tmp_path / "o").exists()  # nothing written, not even the folder


def test_truncated_bag(tmp_path: Path, small_bag: Path) -> None:
    bag = tmp_path / "cut"
    shutil.copytree(small_bag, bag)
    mcap = next(bag.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    proc = peel("residual", str(bag), "--out", str(tmp_path / "o"))
    _one_line_error(proc, "peel record --repair")
    assert not (tmp_path / "o").exists()


def _in_process(capsys: pytest.CaptureFixture[str], *argv: str):
    """``peel residual ARGV`` through the same top-level handler, in this process (argument and
    model checks: no need to import torch again in a subprocess)."""
    code = run_main("peel residual", residual_main, list(argv))
    return subprocess.CompletedProcess(argv, code, "", capsys.readouterr().err)


@pytest.mark.parametrize(("edit", "needle"), [
    (lambda c: c["units"].update(dt_s=0.05), "the model's inputs are 0.05 s apart"),
    (lambda c: c["units"].update(hist_columns=["q_m", "v_mps", "fx_N", "fz_N"]), "its inputs"),
])
def test_model_whose_inputs_do_not_match(tmp_path: Path, small_bag: Path, edit, needle,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    src = shipped_checkpoint()
    shutil.copy(src, tmp_path / "m.safetensors")
    cfg = json.loads(src.with_suffix(".json").read_text())
    edit(cfg)
    (tmp_path / "m.json").write_text(json.dumps(cfg))
    proc = _in_process(capsys, str(small_bag), "--model", str(tmp_path / "m.safetensors"),
                       "--out", str(tmp_path / "o"))
    _one_line_error(proc, needle)
    assert not (tmp_path / "o").exists()


def test_other_bad_arguments(tmp_path: Path, small_bag: Path,
                             capsys: pytest.CaptureFixture[str]) -> None:
    def refused(needle: str, *argv: str) -> None:
        _one_line_error(_in_process(capsys, *argv), needle)

    out = str(tmp_path / "o")
    refused("does not exist", str(tmp_path / "nope"), "--out", out)
    refused("--holdout", str(small_bag), "--holdout", "0.99", "--out", out)
    refused("--seed", str(small_bag), "--seed", "-1", "--out", out)
    refused(f"no such checkpoint: cannot read {tmp_path / 'x.safetensors'}", str(small_bag),
            "--model", str(tmp_path / "x"), "--out", out)
    (tmp_path / "metadata.yaml").write_text("a: 1\n")  # a file, but not a checkpoint
    refused(f"cannot read {tmp_path / 'metadata.yaml'} as a checkpoint", str(small_bag),
            "--model", str(tmp_path / "metadata.yaml"), "--out", out)
    (tmp_path / "p.yaml").write_text(
        "peel_residual:\n  ros__parameters:\n    residual:\n      holdot: 0.2\n")
    refused("unknown parameter 'residual.holdot'", str(small_bag), "--params",
            str(tmp_path / "p.yaml"), "--out", out)
    # the residual group is peel_residual's (config/peel_residual.yaml), not the learner's
    (tmp_path / "learner.yaml").write_text(
        "model_learner_node:\n  ros__parameters:\n    residual:\n      holdout: 0.2\n")
    refused("unknown parameter 'residual.holdout' for model_learner_node", str(small_bag), "--params",
            str(tmp_path / "learner.yaml"), "--out", out)
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    refused("holds no peel run", str(small_bag), "--out", str(tmp_path / "foreign"))
    OutputDir(tmp_path / "done", command="peel residual").create()
    (tmp_path / "done" / "report.json").write_text("{}")
    refused("holds an earlier 'peel residual' run", str(small_bag), "--out",
            str(tmp_path / "done"))
    assert not (tmp_path / "o").exists()
