"""Open-loop fine-tuning of f_theta before the analysis (``peel_residual.adapt``).

Clean level-3 plant tasks under exploratory command profiles (``residual_helpers``, seed 31,
not the report's), the shipped model; the study script's ``--adapt-open-loop`` and
``scripts/open_loop_checkpoint.py`` as real processes.
"""

from __future__ import annotations

import copy
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from residual_helpers import generate_tasks
from safetensors import safe_open

from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_model.compensated import corrected_model
from peel_model.effect_terms import Candidate, Term
from peel_residual.adapt import OpenLoopTune, open_loop_finetune
from peel_residual.data import horizons
from peel_residual.predict import open_loop, open_loop_many, rollout

ROOT = Path(__file__).resolve().parents[1]
SHORT = OpenLoopTune(epochs=3, patience=3, batch=64)


def _params(model) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


def _reference_rollout(model, hz) -> np.ndarray:
    """Algorithm 2 line 9 written out: one window per step, the measured (q, v) and the
    forces predicted so far written into a copy of the recorded rows."""
    rows = torch.as_tensor(hz.rows, dtype=torch.float32).clone()
    t = torch.as_tensor(hz.t, dtype=torch.float32)
    h = model.h
    for k in range(hz.steps):
        kw = {"t_next": t[:, h + k]} if getattr(model, "needs_time", False) else {}
        with torch.no_grad():
            rows[:, h + k, 2:4] = model.predict(rows[:, k:k + h], rows[:, h + k, 1], **kw)
    return rows[:, h:, 2:4].numpy()


def test_the_rollout_feeds_back_its_own_forces() -> None:
    """``predict.open_loop`` (chunked, no gradient) and the differentiable ``rollout`` the
    fine-tuning trains through both equal the rollout written out step by step, for the model
    and for a model with a time term (fed the sample times); the measured forces past the
    history never reach the prediction."""
    torch.set_num_threads(1)
    base = load_checkpoint(shipped_checkpoint())
    timed = corrected_model(base, [Term(Candidate("drift_in_time"), "fz", (0.5,))], 0.1)
    hz = horizons(generate_tasks("plant", n=2, seed=31), base.h, 25, 5)
    for model in (base, timed):
        want = _reference_rollout(model, hz)
        np.testing.assert_allclose(open_loop(model, hz), want, atol=1e-5)
        t = torch.as_tensor(hz.t, dtype=torch.float32)
        ours = rollout(model, torch.as_tensor(hz.rows, dtype=torch.float32), 25, t)
        np.testing.assert_allclose(ours.detach().numpy(), want, atol=1e-5)
    hz.rows[:, base.h:, 2:4] += 100.0
    np.testing.assert_allclose(open_loop(timed, hz), want, atol=1e-5)
    assert not np.allclose(open_loop(base, hz), _reference_rollout(timed, hz), atol=1e-3)


def test_models_rolled_out_together_equal_each_rolled_out_alone(monkeypatch) -> None:
    """``open_loop_many`` (one f_theta call per step on the rows of every model) gives each
    model the rollout it has alone: the plain model, a time term, cross-talk with an offset,
    each on its own horizons, and with batches split at the chunk size, to within float32
    rounding (f_theta's result for a row changes in the last bits with the batch it is in,
    and the rollout feeds it back); models that do not share one f_theta are refused."""
    import peel_residual.predict as P

    torch.set_num_threads(1)
    base = load_checkpoint(shipped_checkpoint())
    models = [base,
              corrected_model(base, [Term(Candidate("drift_in_time"), "fz", (0.5,))], 0.1),
              corrected_model(base, [Term(Candidate("cross_talk"), "fx", (0.05,)),
                                     Term(Candidate("sensor_offset"), "fz", (-1.5,))], 0.1)]
    hz = horizons(generate_tasks("plant", n=3, seed=31), base.h, 25, 5)
    hzs = [hz.subset(hz.task == i) for i in (0, 1, 2)]
    alone = [_reference_rollout(m, z) for m, z in zip(models, hzs, strict=True)]
    assert not np.allclose(alone[1], open_loop(base, hzs[1]), atol=0.1)  # the terms act
    assert not np.allclose(alone[2], open_loop(base, hzs[2]), atol=0.1)
    for chunk in (P._CHUNK, 7):
        monkeypatch.setattr(P, "_CHUNK", chunk)
        together = open_loop_many(models, hzs)
        for got, want in zip(together, alone, strict=True):  # float32 rounding of another
            np.testing.assert_allclose(got, want, atol=2e-3)  # batch, fed back 25 steps
    other = copy.deepcopy(base)
    with pytest.raises(ValueError, match="share one f_theta"):
        open_loop_many([base, other], hzs[:2])


def test_open_loop_finetuning_lowers_the_validation_rollout_error() -> None:
    """On plant tasks the shipped model drifts open loop; a few epochs of the open-loop loss lower
    the validation tasks' rollout MSE, keep the best epoch, leave the input model unchanged, and
    give the same weights when repeated (seeded)."""
    torch.set_num_threads(1)
    model = load_checkpoint(shipped_checkpoint())
    before = _params(model)
    tasks = generate_tasks("plant", n=10, seed=31)
    a = open_loop_finetune(model, tasks[:7], tasks[7:], SHORT)
    assert all(torch.equal(p, q) for p, q in zip(before, model.parameters(), strict=True))
    assert len(a.val_mse) >= 2 and a.best_epoch >= 1
    assert a.val_mse[a.best_epoch] == min(a.val_mse) < 0.95 * a.val_mse[0]
    hz = horizons(tasks[7:], model.h, 25, 5)
    err = (open_loop(a.model, hz) - hz.rows[:, model.h:, 2:4]) ** 2
    assert np.isclose((err * hz.valid[..., None]).sum() / (2 * hz.valid.sum()),
                      a.val_mse[a.best_epoch], rtol=1e-3)  # the kept weights are the best epoch's
    b = open_loop_finetune(model, tasks[:7], tasks[7:], SHORT)
    assert all(torch.equal(p, q) for p, q in
               zip(a.model.parameters(), b.model.parameters(), strict=True))


def _study(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "residual_study.py"), "--out", str(out),
         "--families", "sensor_offset", "--amplitudes", "1", "--tasks", "5", "--draws", "1",
         "--clean", "0", "--source", "sim", "--fresh", "2", "--seed", "3", "--no-progress",
         *extra], capture_output=True, text=True, timeout=600)


def test_the_study_analyses_with_the_open_loop_tuned_model(tmp_path: Path) -> None:
    bad = _study(tmp_path / "bad", "--adapt-open-loop")
    assert bad.returncode == 2 and "--adapt-open-loop needs --adapt K" in bad.stderr
    proc = _study(tmp_path / "ol", "--adapt", "8", "--adapt-open-loop")
    assert proc.returncode == 0, proc.stderr[-3000:]
    model = json.loads((tmp_path / "ol" / "study.json").read_text())["model"]
    tuned = model["open_loop_tuned"]
    assert tuned["val_mse_after"] <= tuned["val_mse_before"]
    meta = json.loads((tmp_path / "ol" / "adapted.json").read_text())["meta"]
    assert meta["open_loop_tuned"]["best_epoch"] == tuned["best_epoch"]
    assert meta["adapted_on"]["tasks"] == 8  # the one-step fine-tuning's record is kept
    with safe_open(str(tmp_path / "ol" / "adapted.safetensors"), framework="pt") as f:
        assert f.keys()


def test_the_model_gap_script_prints_each_models_open_loop_error() -> None:
    cmd = [sys.executable, str(ROOT / "scripts" / "residual_model_gap.py"), "--seed", "3",
           "--tasks", "1"]
    bad = subprocess.run([*cmd, "--model", "x"], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "--model 'x': expected NAME=CHECKPOINT" in bad.stderr
    proc = subprocess.run([*cmd, "--model", "shipped"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["data_seed"] == 555_003 and out["shipped"]["checkpoint"] == "shipped"
    rmse = out["shipped"]["rmse_over_horizon"]
    assert len(rmse) == 2 and all(x > 0 for x in rmse)
    assert out["level"] is None  # plant.level of the config
    bad_level = subprocess.run([*cmd, "--level", "4", "--model", "shipped"], capture_output=True,
                               text=True, timeout=300)
    assert bad_level.returncode == 2 and "--level" in bad_level.stderr
    sim = subprocess.run([*cmd, "--level", "0", "--model", "shipped"], capture_output=True,
                         text=True, timeout=300)
    assert sim.returncode == 0, sim.stderr[-2000:]
    on_sim = json.loads(sim.stdout)
    assert on_sim["level"] == 0 and on_sim["shipped"]["rmse_over_horizon"] != rmse


def _tune(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "open_loop_checkpoint.py"),
                           "--threads", "1", *args], capture_output=True, text=True, timeout=600)


def test_the_open_loop_checkpoint_script_writes_a_tuned_model(tmp_path: Path) -> None:
    bad = _tune("--data", str(tmp_path / "none"), "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "is not a complete peel dataset" in bad.stderr
    assert not list(tmp_path.glob("x*"))
    ds = tmp_path / "ds"
    gen = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "dataset", "--param-sets",
                          "3", "--per-set", "2", "--seed", "4", "--out", str(ds),
                          "--no-progress"], capture_output=True, text=True, timeout=300)
    assert gen.returncode == 0, gen.stderr[-2000:]
    proc = _tune("--data", str(ds), "--out", str(tmp_path / "tuned"), "--epochs", "3")
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert len(out["val_mse"]) == 4 and out["train_tasks"] == 2 and out["val_tasks"] == 2
    assert out["val_mse"][out["best_epoch"]] == min(out["val_mse"])
    again = _tune("--data", str(ds), "--out", str(tmp_path / "tuned"), "--epochs", "1")
    assert again.returncode == 2 and "tuned.safetensors exists" in again.stderr
    meta = json.loads((tmp_path / "tuned.json").read_text())["meta"]
    assert meta["open_loop_tuned"]["tuned_from_sha256"] == hashlib.sha256(
        shipped_checkpoint().read_bytes()).hexdigest()
    assert "dataset" in meta  # the starting model's record is kept
    with safe_open(str(tmp_path / "tuned.safetensors"), framework="pt") as f:
        names = f.keys()
        tensors = {k: f.get_tensor(k) for k in names}
    shipped = load_checkpoint(shipped_checkpoint()).state_dict()
    changed = [k for k, v in tensors.items() if k in shipped and not torch.equal(v, shipped[k])]
    assert bool(changed) == (out["best_epoch"] > 0)
