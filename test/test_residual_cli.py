"""``peel residual`` as a real process on real bags (docs/residual.md).

Plant data with effects the tool is not told about (``peel_sim_node.example_effects``), made
in-process with PeelEnv under exploratory command profiles, written with the project's
BagWriter; the command runs in a subprocess; report.json is read with ``json``, the figures
with matplotlib's PNG reader, the corrected checkpoint with the project's loader.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import matplotlib.image as mpimg
import pytest
from residual_helpers import generate_tasks, peel, write_bag

from model_learner_node.checkpoint import load_checkpoint, shipped_checkpoint
from model_learner_node.compensated import CompensatedPredictor
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
    from peel_msgs_py import topics as T
    from peel_msgs_py.bag import BagWriter
    from peel_msgs_py.runtime import msg as M

    with BagWriter(tmp_path / "clock") as bag:
        bag.add_topic(T.CLOCK, T.topic(T.CLOCK).type, [T.topic(T.CLOCK).qos])
        bag.write(T.CLOCK, M.serialize(M.Clock()), 1_700_000_000_000_000_000)
    proc = peel("residual", str(tmp_path / "clock"), "--out", str(tmp_path / "o"))
    _one_line_error(proc, "has neither /peel/trajectory nor all of")
    assert not (tmp_path / "o" / "report.json").exists()


def test_truncated_bag(tmp_path: Path, small_bag: Path) -> None:
    bag = tmp_path / "cut"
    shutil.copytree(small_bag, bag)
    mcap = next(bag.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    proc = peel("residual", str(bag), "--out", str(tmp_path / "o"))
    _one_line_error(proc, "peel record --repair")


@pytest.mark.parametrize(("edit", "needle"), [
    (lambda c: c["units"].update(dt_s=0.05), "the model's inputs are 0.05 s apart"),
    (lambda c: c["units"].update(hist_columns=["q_m", "v_mps", "fx_N", "fz_N"]), "its inputs"),
])
def test_model_whose_inputs_do_not_match(tmp_path: Path, small_bag: Path, edit, needle) -> None:
    src = shipped_checkpoint()
    shutil.copy(src, tmp_path / "m.safetensors")
    cfg = json.loads(src.with_suffix(".json").read_text())
    edit(cfg)
    (tmp_path / "m.json").write_text(json.dumps(cfg))
    proc = peel("residual", str(small_bag), "--model", str(tmp_path / "m.safetensors"),
                "--out", str(tmp_path / "o"))
    _one_line_error(proc, needle)


def test_other_bad_arguments(tmp_path: Path, small_bag: Path) -> None:
    _one_line_error(peel("residual", str(tmp_path / "nope"), "--out", str(tmp_path / "o")),
                    "does not exist")
    _one_line_error(peel("residual", str(small_bag), "--holdout", "0.99", "--out",
                         str(tmp_path / "o")), "--holdout")
    _one_line_error(peel("residual", str(small_bag), "--model", str(tmp_path / "x"),
                         "--out", str(tmp_path / "o")), "no such checkpoint")
    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "report.json").write_text("{}")
    _one_line_error(peel("residual", str(small_bag), "--out", str(tmp_path / "done")),
                    "already holds a peel residual report")
