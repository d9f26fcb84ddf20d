"""The power study's machinery on small draws, and the held-out decision (docs/residual.md).

Clean tasks from PeelEnv under exploratory command profiles (``residual_helpers``), effects
drawn by ``peel_residual.inject`` and added on the measurement side, analysed
with the shipped model through ``peel_residual.study.run_job``; the study script
run as a real process with 1 and 2 workers. Seeds here (3, 31, 41) are not the report's.
"""

from __future__ import annotations

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
from peel_model.effect_terms import Candidate, Term
from peel_residual.analysis import corrected_model, task_drift
from peel_residual.config import load_residual_config
from peel_residual.data import horizons
from peel_residual.decide import consistency_check, held_out_decision, holm_pass, open_loop_rmse
from peel_residual.inject import SHAPE_RANGES, SPEED_RANGES, TASK_OFFSET, Injection, draw
from peel_residual.study import CLEAN, Job, plan_jobs, run_job, summarise
from peel_sim_node.example_effects import SpeedError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def model():
    torch.set_num_threads(1)
    return load_checkpoint(shipped_checkpoint())


@pytest.fixture(scope="module")
def cfg():
    return load_residual_config()


@pytest.fixture(scope="module")
def plant10():
    return generate_tasks("plant", n=10, seed=31)


@pytest.fixture(scope="module")
def fresh():
    return generate_tasks("plant", n=3, seed=41)


def test_draws_are_seeded_and_inside_the_stated_ranges() -> None:
    for fam in (*SHAPE_RANGES, TASK_OFFSET):
        a = [draw(fam, 1.5, np.random.default_rng([7, i])) for i in range(20)]
        b = [draw(fam, 1.5, np.random.default_rng([7, i])) for i in range(20)]
        assert a == b
        assert {x.channel for x in a} == {"fx", "fz"}
        for x in a:
            for name, v in x.shape.items():
                lo, hi = SHAPE_RANGES[fam][name]
                assert lo <= v <= hi
            assert abs(x.amplitude_n) == 1.5 or (fam == TASK_OFFSET
                                                 and 0.3 <= abs(x.amplitude_n) <= 0.5)
    for fam, (lo, hi) in SPEED_RANGES.items():
        a = [draw(fam, 1.5, np.random.default_rng([7, i])) for i in range(20)]
        assert a == [draw(fam, 1.5, np.random.default_rng([7, i])) for i in range(20)]
        assert {x.channel for x in a} == {"v"} and all(x.plant_side for x in a)
        assert all(lo <= abs(x.amplitude_n) <= hi for x in a)
        assert {np.sign(x.amplitude_n) for x in a} == {-1.0, 1.0}
    jobs = plan_jobs(["viscous_drag", TASK_OFFSET, "speed_scale"], [1.0, 2.0], [10], draws=2,
                     clean=3, seed=5)
    assert [j.family for j in jobs].count(CLEAN) == 3
    for fam in (TASK_OFFSET, "speed_scale"):  # once per task count, not per amplitude
        assert [j.family for j in jobs].count(fam) == 2
    assert len({j.index for j in jobs}) == len(jobs)


def test_injection_adds_exactly_the_drawn_shape(plant10) -> None:
    inj = Injection("periodic_adhesion", "fz", -1.5, {"lambda_mm": 5.0, "phase_rad": 0.3})
    out = inj.apply(plant10)
    for a, b in zip(plant10, out, strict=True):
        assert np.array_equal(a.fx, b.fx)
        assert np.allclose(b.fz - a.fz, -1.5 * np.sin(2 * np.pi * a.q / 5.0 + 0.3))
    off = Injection(TASK_OFFSET, "fx", 0.4).apply(plant10)
    steps = [float(np.mean(b.fx - a.fx)) for a, b in zip(plant10, off, strict=True)]
    assert np.allclose(np.diff(steps), 0.4)
    assert all(np.ptp(b.fx - a.fx) < 1e-12 for a, b in zip(plant10, off, strict=True))


def test_a_drawn_effect_is_named(plant10, fresh, model, cfg) -> None:
    job = Job(0, "periodic_adhesion", 2.0, 10, 31, 3)
    rec = run_job(job, plant10, fresh, model, cfg)
    inj = rec["injection"]
    assert rec["detected"], rec
    assert any(n.startswith("periodic_adhesion") and n.endswith("@" + inj["channel"])
               for n in rec["named"])
    ch = inj["channel"]
    assert rec["heldout_open_loop_ratio"][ch] < 0.9
    assert rec["fresh_open_loop_ratio"][ch] < 0.9  # on tasks the analysis never saw


def test_a_drawn_speed_error_is_recorded_in_the_plant_and_named(model, cfg) -> None:
    """A speed draw is not a rewrite of the data: the tasks are recorded with the robot at
    u (1 + s), the forces answer the speed it really has, and the family is named on v."""
    job = Job(1, "speed_scale", 0.0, 10, 31, 3)
    inj = job.injection()
    assert inj.speed_error() == (pytest.approx(1.0 + inj.amplitude_n), 0.0)
    assert 0.05 <= abs(inj.amplitude_n) <= 0.30
    with pytest.raises(ValueError, match="acts in the plant"):
        inj.apply(generate_tasks("plant", n=1, seed=31))
    slip = [SpeedError(*inj.speed_error())]
    tasks = generate_tasks("plant", slip, n=10, seed=31)
    clean = generate_tasks("plant", n=10, seed=31)
    for a, b in zip(tasks, clean, strict=True):  # the same commands (to the last sample), ...
        n = min(len(a), len(b)) - 1
        assert np.array_equal(a.u[:n], b.u[:n])
        assert not np.allclose(a.q[1:n], b.q[1:n])  # ... another motion
    rec = run_job(job, tasks, generate_tasks("plant", slip, n=3, seed=41), model, cfg)
    assert rec["detected"] and "speed_scale@v" in rec["named_families"], rec
    assert "fresh_open_loop_ceiling" not in rec  # exact for measurement-side effects only
    assert rec["fresh_open_loop_ratio"]["v"] < 1.0


def test_a_between_task_drift_is_flagged(plant10, fresh, model, cfg) -> None:
    job = Job(1, TASK_OFFSET, 0.0, 10, 31, 3)
    rec = run_job(job, plant10, fresh, model, cfg)
    assert rec["detected"] and rec["task_drift"][rec["injection"]["channel"]], rec
    clean = run_job(Job(2, CLEAN, 0.0, 10, 31, 3), plant10, fresh, model, cfg)
    assert not any(clean["task_drift"].values()), clean
    # the drifting channel is flagged, not the other (these clean tasks' own first-sample F_RZ
    # trend is +0.16 N/task, p = 0.04: at 10 tasks a -0.35 N/task drift on F_RZ is not found)
    for ch, other in (("fx", "fz"), ("fz", "fx")):
        d = task_drift(model, Injection(TASK_OFFSET, ch, 0.4).apply(plant10), model.h, cfg)
        assert d[ch]["drift"] and not d[other]["drift"], d
        assert d[ch]["slope_n_per_task"] == pytest.approx(0.4, abs=0.2)


def test_clean_simulator_data_claims_nothing(model, cfg) -> None:
    tasks, fresh_sim = generate_tasks("sim", n=8, seed=3), generate_tasks("sim", n=2, seed=4)
    rec = run_job(Job(0, CLEAN, 0.0, 8, 3, 3), tasks, fresh_sim, model, cfg)
    assert rec["detected"] is None and not rec["claimed"], rec
    assert rec["named"] == []
    s = summarise([rec])
    assert s["clean"][0]["false_alarm_rate"] == 0.0 and s["power"] == []


def test_a_term_that_worsens_the_held_out_open_loop_is_never_kept(plant10, model, cfg) -> None:
    """On data with a true +1.5 N F_RZ offset: the true term is kept, a wrong F_RX offset (it
    raises F_RX's held-out open-loop error) is dropped, and no channel ends worse."""
    data = Injection("sensor_offset", "fz", 1.5).apply(plant10)
    hz = horizons(data[:4], model.h, cfg.horizon_steps, cfg.stride)
    good = Term(Candidate("sensor_offset"), "fz", (1.5,))
    bad = Term(Candidate("sensor_offset"), "fx", (3.0,))
    base = open_loop_rmse(model, hz)
    assert open_loop_rmse(corrected_model(model, [good, bad], 0.1), hz)["fx"] > base["fx"]
    kept, dropped = held_out_decision(model, [good, bad], hz, 0.1)
    assert kept == [good] and [t for t, _ in dropped] == [bad]
    assert "held-out open-loop error of fx worse" in dropped[0][1]
    after = open_loop_rmse(corrected_model(model, kept, 0.1), hz)
    assert all(after[ch] <= base[ch] for ch in base)
    assert after["fz"] < base["fz"]


def test_holm_step_down_passes_in_order_of_p() -> None:
    p = np.array([0.04, 0.01, 0.02])
    assert holm_pass(p, 0.05, 3).tolist() == [True, True, True]  # 0.01<=.0167 .02<=.025 .04<=.05
    assert holm_pass(np.array([0.03, 0.01]), 0.05, 3).tolist() == [False, True]  # 0.03 > 0.025
    assert not holm_pass(np.array([0.02, 0.03]), 0.05, 3).any()  # smallest 0.02 > 0.0167


def test_a_term_must_help_consistently_across_the_held_out_tasks(plant10, model) -> None:
    """``residual.heldout_alpha``: the true +1.5 N F_RZ offset lowers every held-out task's
    open-loop error; on 6 held-out tasks that passes at 0.05 (p = 1/64), on 3 it cannot
    (the smallest p is 1/8) and the term is dropped with the test named."""
    data = Injection("sensor_offset", "fz", 1.5).apply(plant10)
    good = Term(Candidate("sensor_offset"), "fz", (1.5,))
    hz6 = horizons(data[:6], model.h, 25, 5)
    kept, dropped = consistency_check(model, [good], hz6, 0.1, 0.05)
    assert kept == [good] and dropped == []
    hz3 = horizons(data[:3], model.h, 25, 5)
    kept, dropped = consistency_check(model, [good], hz3, 0.1, 0.05)
    assert kept == [] and [t for t, _ in dropped] == [good]
    assert "consistently across the 3 held-out tasks (Wilcoxon p = 0.125" in dropped[0][1]


def _study_script(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "residual_study.py"), "--out", str(out),
         "--families", f"sensor_offset,{TASK_OFFSET},speed_offset", "--amplitudes", "1", "--tasks", "5", "--draws", "1",
         "--clean", "1", "--source", "sim", "--fresh", "2", "--seed", "3", "--no-progress",
         *extra], capture_output=True, text=True, timeout=600)


def test_the_study_script_is_independent_of_the_worker_count(tmp_path: Path) -> None:
    """With the shipped model, and with ``--adapt`` (the shipped model fine-tuned on clean tasks
    of their own seed, saved beside the study, loaded by every worker): 1 and 2 workers give the
    same runs, and the adapted model's differ from the shipped model's."""
    bad = _study_script(tmp_path / "bad", "--adapt", "4")
    assert bad.returncode == 2 and "--adapt needs at least 8 tasks" in bad.stderr
    assert not (tmp_path / "bad").exists()
    runs = {}
    for name, extra in (("shipped", ()), ("w1", ("--adapt", "8")),
                        ("w2", ("--adapt", "8", "--workers", "2"))):
        proc = _study_script(tmp_path / name, *extra)
        assert proc.returncode == 0, proc.stderr[-3000:]
        runs[name] = json.loads((tmp_path / name / "study.json").read_text())
    model = runs["w1"]["model"]
    path = tmp_path / "w1" / "adapted.safetensors"
    assert model["checkpoint"] == "adapted.safetensors" and model["adapted_on_tasks"] == 8
    assert model["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert model["sha256"] == runs["w2"]["model"]["sha256"]  # the same fine-tuning, seeded
    with safe_open(str(path), framework="pt") as f:  # an independent reader
        assert f.keys()
    assert model["val_rmse_after"] < model["val_rmse_before"]

    def strip(study: dict) -> list[dict]:
        return [{k: v for k, v in r.items() if k != "wall_s"} for r in study["runs"]]

    assert strip(runs["w1"]) == strip(runs["w2"])
    assert [r["heldout_open_loop_rmse_before"] for r in runs["w1"]["runs"]] != [
        r["heldout_open_loop_rmse_before"] for r in runs["shipped"]["runs"]]
    shipped = runs["shipped"]
    assert shipped["model"] == {"checkpoint": "shipped"}
    assert [r["family"] for r in shipped["runs"]] == ["sensor_offset", TASK_OFFSET,
                                                      "speed_offset", CLEAN]
    md = (tmp_path / "shipped" / "study.md").read_text()
    assert "| clean data, tasks |" in md and "| speed_offset | ± 0.1-0.4 mm/s |" in md
    assert len((tmp_path / "shipped" / "runs.jsonl").read_text().splitlines()) == 4
    assert len(shipped["summary"]["power"]) == 3 and shipped["summary"]["clean"][0]["runs"] == 1
    speed = [p for p in shipped["summary"]["power"] if p["family"] == "speed_offset"]
    assert "reachable" not in speed[0]  # the exact ceiling holds for measurement-side effects


def test_the_drift_null_script_flags_what_the_analysis_flags(tmp_path: Path) -> None:
    """``scripts/residual_drift_null.py`` reads the first samples the study records
    (``exploratory_tasks``), applies the analysis' own start-force test, and counts it; a bad
    ``--seeds`` is one line and exit 2."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        from residual_drift_null import first_samples
    finally:
        sys.path.pop(0)
    from peel_residual.analysis import start_force_drift
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.episode import exploratory_tasks

    tasks = exploratory_tasks(load_sim_config(), source="plant", n=3, seed=41)
    assert first_samples(41, 3, None).tolist() == [[t.fx[0], t.fz[0]] for t in tasks]
    start = first_samples(41, 12, None)
    drifting = start + np.outer(0.4 * np.arange(12), [1.0, 0.0])  # +0.4 N per task on F_RX
    flags = start_force_drift(drifting, 0.01)
    assert flags[0]["drift"] and flags[0]["slope_n_per_task"] == pytest.approx(0.4, abs=0.2)
    script = [sys.executable, str(ROOT / "scripts" / "residual_drift_null.py")]
    bad = subprocess.run([*script, "--out", str(tmp_path / "bad"), "--seeds", "5:5"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "empty range '5:5'" in bad.stderr
    proc = subprocess.run([*script, "--out", str(tmp_path), "--seeds", "41:44", "--tasks", "12"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    row = json.loads((tmp_path / "drift_null.json").read_text())["rows"][0]
    assert row["n_tasks"] == 12 and row["seeds"] == 3 and row["alpha"] == 0.01
    expect = [start_force_drift(first_samples(s, 12, None), 0.01) for s in (41, 42, 43)]
    assert [r["p"] for r in row["runs"]] == [[f["p"] for f in e] for e in expect]
    assert row["flagged"]["either"] == sum(any(f["drift"] for f in e) for e in expect)
    assert "| 12 | 3 | 0.01 |" in (tmp_path / "drift_null.md").read_text()
