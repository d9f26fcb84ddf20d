"""A corrected model in the node graph and in ``peel experiment``, and ``--effect``.

``peel graph`` on the plant with an undeclared effect (``--effect``) and a model with a
compensation term: the planner plans with it (its rollouts carry the terms), the learner adapts
f_theta with MAML and swaps each update in over the planner's service like any checkpoint, the
terms held; the bag shows the effect (the robot at 75 % of the command). ``peel experiment``
does the same in-process. A name that does not import is a one-line error, exit 2.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from graph_helpers import ALONE, FAST, SIM_TASKS, node_env, override_yaml
from residual_helpers import peel

from model_learner_node.synthetic import synthetic_trajectory
from peel_bag.bagread import read_trajectories
from peel_model.checkpoint import load_checkpoint, save_checkpoint
from peel_model.compensated import CompensatedPredictor
from peel_model.config import ModelConfig
from peel_model.effect_terms import Candidate, Term
from peel_model.predictor import ForcePredictor, fit_normalization

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

EFFECT = "peel_sim_node.example_effects:slipping_axis"
TERMS = [Term(Candidate("near_start_hold", 4.0), "fz", (1.0,)),
         Term(Candidate("decay_in_time", 2.0), "fx", (0.5,)),
         Term(Candidate("actuator_lag"), "v", (0.5,))]

def _override(model: Path) -> str:
    return override_yaml(SIM_TASKS, FAST, ALONE, {
        "/**": {"task": {"q_ter_mm": 5.0}},
        "peel_planner_node": {"model": {"path": model}},
        "model_learner_node": {"node": {"init_model": model}},
        "peel_bringup": {"graph": {"final_model_wait_s": 120.0}},
    })


def corrected(tmp: Path, cfg: ModelConfig | None = None) -> Path:
    """A seeded f_theta with three compensation terms, saved as a checkpoint."""
    torch.manual_seed(0)
    cfg = cfg or ModelConfig()
    base = ForcePredictor(cfg, fit_normalization([synthetic_trajectory(i) for i in range(3)],
                                                 cfg.h))
    return save_checkpoint(tmp / "corrected.safetensors", CompensatedPredictor(base, TERMS))


def speed_ratio(trajs) -> float:
    """The robot's steady-state speed over the command, b / (1 - a) of the least-squares fit
    v_{k+1} = a v_k + b u_k over every sample (a first-order actuator lag, which the plant has,
    changes a and b but not the ratio)."""
    x = np.concatenate([np.stack([tr.v[:-1], tr.u[:-1]], axis=1) for tr in trajs])
    y = np.concatenate([tr.v[1:] for tr in trajs])
    (a, b), *_ = np.linalg.lstsq(x, y, rcond=None)
    return float(b / (1.0 - a))


def test_graph_plans_learns_and_swaps_a_corrected_model_with_an_effect(
        tmp_path: Path, ros_domain: str) -> None:
    model = corrected(tmp_path)
    override = tmp_path / "override.yaml"
    override.write_text(_override(model))
    env = node_env()
    bag = tmp_path / "bag"
    proc = subprocess.run(
        [sys.executable, "-m", "peel_bringup.cli", "graph", "--plant", "plant", "--tasks", "2",
         "--params", str(override), "--out", str(tmp_path / "run"), "--seed", "4",
         "--record", str(bag), "--effect", EFFECT],
        env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["effects"] == [EFFECT] and len(summary["results"]) == 2
    assert {1, 2} <= set(summary["model_versions"]), summary  # the learner's swaps, accepted
    for v in (1, 2):
        swapped = load_checkpoint(tmp_path / "run" / "models" / f"model_v{v:04d}.safetensors")
        assert isinstance(swapped, CompensatedPredictor) and swapped.terms == tuple(TERMS)
    adapted = load_checkpoint(tmp_path / "run" / "models" / "model_v0002.safetensors")
    first = load_checkpoint(model)
    assert any(not torch.equal(a, b) for a, b in
               zip(adapted.base.state_dict().values(), first.base.state_dict().values(),
                   strict=True))
    trajs = read_trajectories(bag)
    assert len(trajs) == 2
    assert 0.65 < speed_ratio(trajs) < 0.85  # the injected slipping axis is in the data


def test_graph_refuses_an_effect_that_does_not_import(tmp_path: Path) -> None:
    proc = peel("graph", "--tasks", "1", "--out", str(tmp_path / "run"), "--effect",
                "no_such_module_xyz:f", timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot import 'no_such_module_xyz'" in lines[0], proc.stderr
    assert not (tmp_path / "run" / "summary.json").exists()


def test_experiment_with_a_corrected_model_and_an_effect(tmp_path: Path) -> None:
    model = corrected(tmp_path, ModelConfig(h=4, conv_channels=2, attention_hidden=2,
                                            lstm_hidden=4, fc=(8,)))
    (tmp_path / "sim.yaml").write_text(
        "peel_sim_node:\n  ros__parameters:\n    task:\n      t_max_s: 6.0\n")
    (tmp_path / "learner.yaml").write_text(
        "model_learner_node:\n  ros__parameters:\n    maml:\n      meta_steps: 1\n"
        "      support_slices: 4\n      query_slices: 4\n")
    out = tmp_path / "exp"
    proc = peel("experiment", "--tasks", "2", "--methods", "ol-mppi", "--no-oracle", "--seed",
                "2", "--checkpoint", str(model), "--effect", EFFECT, "--n-samples", "6",
                "--horizon", "2", "--sim-params", str(tmp_path / "sim.yaml"),
                "--learner-params", str(tmp_path / "learner.yaml"), "--out", str(out),
                timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert res["effects"] == [EFFECT]
    tr = res["traces"]["ol-mppi"]
    trace = SimpleNamespace(v=np.array(tr["v"]), u=np.array(tr["u"]))
    assert 0.65 < speed_ratio([trace]) < 0.85
    saved = load_checkpoint(res["task20_model"])
    assert isinstance(saved, CompensatedPredictor) and saved.terms == tuple(TERMS)
    bad = peel("experiment", "--tasks", "1", "--out", str(tmp_path / "o"), "--effect",
               "peel_sim_node.example_effects:nothing_here", timeout=60)
    assert bad.returncode == 2 and "has no 'nothing_here'" in bad.stderr.strip().splitlines()[0]
