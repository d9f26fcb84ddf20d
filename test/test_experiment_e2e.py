"""`peel experiment` and `peel experiment sweep` end to end, as real processes, on the plant.

A tiny forward model, 2 tasks, small N/H and a short t_max keep this to seconds; every file is
read back with an independent library (json, matplotlib's PNG reader, safetensors)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import pytest
import torch
from safetensors.numpy import load_file

from model_learner_node.synthetic import synthetic_trajectory
from peel_model.checkpoint import load_checkpoint, save_checkpoint
from peel_model.config import ModelConfig
from peel_model.predictor import ForcePredictor, fit_normalization

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

TASK_KEYS = {"cost", "t_cpl", "sum_fx", "sum_fz", "outcome", "model_version", "update_s"}
METHODS = ["ol-mppi", "baseline1", "baseline2"]


def _peel(*args: str, timeout: float = 400) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", *args],
                          capture_output=True, text=True, timeout=timeout, check=False)


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("exp")
    torch.manual_seed(0)
    cfg = ModelConfig(h=4, conv_channels=2, attention_hidden=2, lstm_hidden=4, fc=(8,))
    model = ForcePredictor(cfg, fit_normalization([synthetic_trajectory(i) for i in range(3)], 4))
    ckpt = save_checkpoint(d / "tiny.safetensors", model, meta={"purpose": "test"})
    (d / "sim.yaml").write_text(
        "peel_sim_node:\n  ros__parameters:\n    task:\n      t_max_s: 6.0\n")
    (d / "planner.yaml").write_text(
        "peel_planner_node:\n  ros__parameters:\n    task:\n      t_max_s: 6.0\n")
    (d / "learner.yaml").write_text(
        "model_learner_node:\n  ros__parameters:\n    maml:\n      meta_steps: 2\n"
        "      support_slices: 8\n      query_slices: 8\n    baseline2:\n      steps: 3\n")
    return {"dir": d, "ckpt": ckpt, "sim": d / "sim.yaml", "planner": d / "planner.yaml",
            "learner": d / "learner.yaml"}


def _small(setup: dict[str, Path]) -> list[str]:
    return ["--n-samples", "6", "--horizon", "2", "--sim-params", str(setup["sim"]),
            "--planner-params", str(setup["planner"])]


@pytest.fixture(scope="module")
def experiment(setup: dict[str, Path]) -> dict:
    out = setup["dir"] / "out"
    proc = _peel("experiment", "--tasks", "2", "--methods", ",".join(METHODS), "--seed", "3",
                 "--out", str(out), "--checkpoint", str(setup["ckpt"]), "--workers", "2",
                 "--learner-params", str(setup["learner"]), *_small(setup))
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {"out": out, "stdout": json.loads(proc.stdout), "stderr": proc.stderr}


def test_results_json_has_every_method_the_oracle_and_every_key(experiment: dict) -> None:
    res = json.loads((experiment["out"] / "results.json").read_text())
    assert set(res["methods"]) == {*METHODS, "oracle"}
    for m, entry in res["methods"].items():
        tasks = entry["tasks"]
        assert len(tasks) == 2, m
        for k, rec in enumerate(tasks):
            assert set(rec) >= TASK_KEYS, (m, set(TASK_KEYS) - set(rec))
            assert rec["task"] == k + 1
            assert rec["outcome"] in {"done", "timeout", "safety_stop"}
            assert rec["t_cpl"] > 0 and rec["sum_fx"] > 0 and rec["sum_fz"] > 0
    # every method peeled the same substrates
    subs = {m: [t["substrate"] for t in e["tasks"]] for m, e in res["methods"].items()}
    assert all(s == subs["oracle"] for s in subs.values())
    assert subs["oracle"][0] != subs["oracle"][1]
    # versions: learners update between peels, baseline 1 and the oracle never
    ol = res["methods"]["ol-mppi"]["tasks"]
    assert [t["model_version"] for t in ol] == [0, 1]
    assert ol[0]["update_s"] == 0 and ol[1]["update_s"] > 0
    assert ol[0]["update"]["updated"] is True
    assert [t["model_version"] for t in res["methods"]["baseline2"]["tasks"]] == [0, 1]
    assert [t["model_version"] for t in res["methods"]["baseline1"]["tasks"]] == [0, 0]
    assert set(res["table1"]) == {*METHODS, "oracle"}
    assert set(res["gap_to_oracle"]) == set(METHODS)
    g = res["gap_to_oracle"]["ol-mppi"]["abs"][1]
    assert g == pytest.approx(ol[1]["cost"] - res["methods"]["oracle"]["tasks"][1]["cost"])
    assert res["timing"]["ol_mppi_update_s_mean"] > 0
    assert "experiment" in experiment["stderr"]  # tqdm progress
    assert experiment["stdout"]["targets"] == res["targets"]


def test_figures_tables_report_and_saved_model(experiment: dict) -> None:
    out = experiment["out"]
    for name in ("fig11_cost_per_task.png", "fig12_task_traces.png"):
        img = mpimg.imread(out / name)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    report = (out / "report.md").read_text()
    for needle in ("Fig. 11", "Table 1", "Fig. 12", "oracle", "fig11_cost_per_task.png",
                   "| baseline2 |", "within 10%"):
        assert needle in report
    assert "| ol-mppi | 2 |" in (out / "table1.md").read_text()
    model = Path(json.loads((out / "results.json").read_text())["task20_model"])
    assert model.is_file() and model.suffix == ".safetensors"
    tensors = load_file(model)  # independent reader
    assert any(k.startswith("body.") for k in tensors)
    assert load_checkpoint(model).h == 4


def test_results_do_not_depend_on_worker_count(setup: dict[str, Path], experiment: dict) -> None:
    from peel_experiments.experiment import Setup, planner_params, run_job

    res = json.loads((experiment["out"] / "results.json").read_text())
    pparams = planner_params(n_samples=6, horizon=2, lam=0.1,
                             planner_overrides=str(setup["planner"]))
    st = Setup(checkpoint=str(setup["ckpt"]), tasks=2, planner_params=pparams,
               sim_overrides=str(setup["sim"]), learner_overrides=str(setup["learner"]),
               save_model=False)
    for method in ("ol-mppi", "oracle"):
        serial = run_job(method, 3, st)
        for a, b in zip(serial["tasks"], res["methods"][method]["tasks"], strict=True):
            assert a["cost"] == b["cost"] and a["t_cpl"] == b["t_cpl"], method


def test_sweep_writes_table2(setup: dict[str, Path], experiment: dict) -> None:
    model = json.loads((experiment["out"] / "results.json").read_text())["task20_model"]
    out = setup["dir"] / "sweep"
    proc = _peel("experiment", "sweep", "--checkpoint", model, "--seeds", "0,1", "--n", "4,8",
                 "--h", "1,2", "--lambdas", "0.1,0.5", "--out", str(out), *_small(setup))
    assert proc.returncode == 0, proc.stderr[-3000:]
    table = json.loads((out / "table2.json").read_text())["table2"]
    assert [e["value"] for e in table["N"]] == [4, 8]
    assert [e["value"] for e in table["H"]] == [1, 2]
    assert [e["value"] for e in table["lambda"]] == [0.1, 0.5]
    for entries in table.values():
        for e in entries:
            assert e["n"] == 2 and e["cost_min"] <= e["cost_mean"] <= e["cost_max"]
            assert e["cost_std"] >= 0
    md = (out / "table2.md").read_text()
    assert "| N | 4 |" in md and "| lambda | 0.5 |" in md
    assert mpimg.imread(out / "table2.png").ndim == 3


@pytest.mark.parametrize(("args", "needle"), [
    (["--methods", "ol-mppi,magic"], "unknown method 'magic'"),
    (["--checkpoint", "/nonexistent/model.safetensors"], "not found"),
    (["--lambda", "-1"], "lambda"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, args: list[str], needle: str) -> None:
    proc = _peel("experiment", "--tasks", "1", "--out", str(tmp_path / "o"), *args, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], proc.stderr
    assert not (tmp_path / "o" / "results.json").exists()


def test_grid_runs_cells_and_writes_one_report(setup: dict[str, Path]) -> None:
    """`peel experiment grid`: one cell run, then a report-only call that adds a cell it has
    not run (listed as missing, nothing peeled); files read back by json and matplotlib."""
    out = setup["dir"] / "grid"
    common = ["--tasks", "2", "--seeds", "0,1", "--out", str(out), "--checkpoint",
              str(setup["ckpt"]), "--workers", "2", "--learner-params", str(setup["learner"]),
              *_small(setup)]
    proc = _peel("experiment", "grid", "--levels", "3", "--sequences", "drift", *common)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cell = json.loads((out / "L3_drift" / "results.json").read_text())
    assert cell["plant"]["level"] == 3 and cell["sequence"] == "drift"
    fr = [t["substrate"]["friction"] for t in cell["runs"]["0"]["oracle"]["tasks"]]
    from peel_experiments.experiment import substrates
    from peel_sim_node.config import load_sim_config

    want = substrates(load_sim_config(str(setup["sim"])), 0, 2, level=3, sequence="drift")
    assert fr == [p["friction"] for p in want]
    summary = json.loads((out / "summary.json").read_text())
    c = summary["cells"]["L3_drift"]
    assert c["headroom"]["n"] == 2 and c["headroom"]["ci95"] is not None  # two seeds: an interval
    for m in ("ol-mppi", "baseline1", "baseline2", "oracle"):
        assert c["metrics"][m]["peels"] == 4
        assert set(c["metrics"][m]) >= {"cost", "t_cpl", "sum_fx", "sum_fz", "peak_force",
                                        "safety_stops"}
    proc = _peel("experiment", "grid", "--levels", "3,0", "--sequences", "drift",
                 "--report-only", *common)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["missing"] == ["L0_drift"] and not (out / "L0_drift").exists()
    assert "L3_drift" in summary["cells"]
    md = (out / "summary.md").read_text()
    assert "Cells not run: L0_drift" in md and "| 3 | drift | ol-mppi |" in md
    for png in ("headroom.png", "fig11_levels.png"):
        assert mpimg.imread(out / png).shape[2] in (3, 4)
    proc = _peel("experiment", "grid", "--levels", "3", "--sequences", "drift", "--report-only",
                 "--methods", "ol-mppi-fast,ol-mppi,baseline1,baseline2", *common)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((out / "summary.json").read_text())["missing"] == ["L3_drift"]  # other arms
    for wrong in (["--levels", "7"], ["--methods", "ol-mppi,magic"]):
        bad = _peel("experiment", "grid", *wrong, *common)
        assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
