"""The fast step inside the peel (model_learner_node.fast_step, .in_peel): Eq. 26 from the prior
on the running task's own samples, used only when it predicts the newest samples better.

The plant is the simulator with a resistance the pretrained model lacks (``hose_drag`` of
peel_sim_node.example_effects: 0.8 N per mm/s of the command, seen in F_RX); the peel is planned
by the shipped model, and the fast step is replayed on its growing prefix as the learner node
takes it, every control period.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from model_learner_node.fast_step import FastStepConfig, FastStepper
from model_learner_node.in_peel import InPeel
from peel_experiments.fast_arm import in_use_errors
from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_model.versions import ModelLedger
from peel_msgs_py.modelinfo import ModelRecord, UpdateWait
from peel_msgs_py.trajectory import Trajectory

CFG = FastStepConfig(fast_every=5)  # the shipped online.* values, one step per control period


@pytest.fixture(scope="module")
def peel() -> Trajectory:
    """One peel of the level-0 plant with the hose drag, planned by the shipped model."""
    from peel_experiments.oracle import learned_planner
    from peel_planner_node.config import load_planner_config
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv
    from peel_sim_node.episode import run_episode
    from peel_sim_node.example_effects import hose_drag

    torch.set_num_threads(1)
    cfg = load_sim_config()
    env = PeelEnv(cfg, source="plant", seed=11, level=0, effects=[hose_drag])
    pcfg = load_planner_config().replace(**{"mppi.n_samples": 16, "mppi.horizon": 3})
    planner = learned_planner(load_checkpoint(shipped_checkpoint()), pcfg)
    planner.reset()
    try:
        return run_episode(env, planner.plan, seed=11)
    finally:
        env.close()


def replay(stepper: FastStepper, traj: Trajectory) -> list[tuple[int, torch.nn.Module]]:
    """The fast step on every control period's prefix; the (samples, model) of each swap."""
    stepper.start(1)
    swaps = []
    for n in range(5, len(traj) + 1, 5):
        res = stepper.observe(traj.slice(0, n))
        if res is not None and res.accepted:
            swaps.append((n, stepper.model))
    return swaps


def second_half_rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e[len(e) // 2:] ** 2)))


def test_the_fast_step_lowers_the_error_on_an_effect_the_model_lacks(peel: Trajectory) -> None:
    """Over the task's second half the model in use predicts the plant better than the
    pretrained one on the same samples, and the prior itself is not changed."""
    prior = load_checkpoint(shipped_checkpoint())
    before = copy.deepcopy(prior.state_dict())
    stepper = FastStepper(prior, CFG)
    swaps = replay(stepper, peel)
    assert swaps, [r.as_dict() for r in stepper.results]
    e_use = in_use_errors(peel, prior, swaps)
    e_pre = in_use_errors(peel, prior, [])
    assert second_half_rms(e_use) < 0.9 * second_half_rms(e_pre), (
        second_half_rms(e_use), second_half_rms(e_pre))
    assert all(torch.equal(before[k], v) for k, v in prior.state_dict().items())
    for r in stepper.results:  # each check is on samples the step was not fitted on
        assert r.fit_end == r.n_samples - CFG.fast_holdout
        assert r.accepted == (r.error_fast_n < (1 - CFG.fast_margin) * r.error_in_use_n)


def test_a_fast_step_that_predicts_worse_is_not_used(peel: Trajectory) -> None:
    """A step size that diverges (no gradient clip): every fast step is checked worse and
    refused; the model in use stays the prior (the planner keeps planning on it)."""
    prior = load_checkpoint(shipped_checkpoint())
    stepper = FastStepper(prior, FastStepConfig(fast_every=5, fast_alpha=1.0,
                                                fast_grad_clip=0.0))
    assert replay(stepper, peel) == []
    assert stepper.results and not any(r.accepted for r in stepper.results)
    assert all(not r.error_fast_n < r.error_in_use_n for r in stepper.results)
    assert stepper.model is prior


def feed(in_peel: InPeel, traj: Trajectory, task: int, upto: int) -> list[Trajectory]:
    """Samples 0..upto-1 of ``traj`` as task ``task`` (0-based), parts in a shuffled order."""
    due = []
    for k in range(upto):
        stamp = int((100.0 + traj.t[k]) * 1e9)
        parts = [{"q_mm": float(traj.q[k])}, {"v_mmps": float(traj.v[k])},
                 {"fx_n": float(traj.fx[k]), "fz_n": float(traj.fz[k])}]
        for p in parts[k % 3:] + parts[: k % 3]:
            got = in_peel.add(stamp, task, **p)
            if got is not None:
                due.append(got)
    return due


def test_in_peel_names_the_fast_step_and_never_offers_an_ended_task(peel: Trajectory,
                                                                    tmp_path: Path) -> None:
    """The node's core: the running task is rebuilt from the per-sample parts; an accepted
    fast model is written with its identity (producer, task, step, samples), which the
    planner's ledger carries into /peel/model_info without ending the wait for an update
    between peels; once the task has ended nothing of it is written."""
    prior = load_checkpoint(shipped_checkpoint())
    in_peel = InPeel(FastStepper(prior, CFG), tmp_path, "/model_learner_node")
    due = feed(in_peel, peel, 0, len(peel))
    assert [len(d) for d in due] == list(range(30, len(peel) + 1, 5))
    last = due[-1]
    for name in ("t", "q", "v", "fx", "fz"):
        np.testing.assert_allclose(getattr(last, name), getattr(peel, name)[: len(last)],
                                   atol=1e-9, err_msg=name)
    paths = [p for p in (in_peel.step(d)[1] for d in due) if p is not None]
    assert len(paths) == sum(r.accepted for r in in_peel.stepper.results) > 0
    meta = json.loads(paths[-1].with_suffix(".json").read_text())["meta"]
    assert meta["producer"] == "/model_learner_node" and "task" not in meta
    used = [r for r in in_peel.stepper.results if r.accepted][-1]
    assert meta["fast_step"] == used.identity() == {
        "task": 1, "step": used.step, "fit_samples": [0, used.fit_end],
        "check_samples": [used.fit_end, used.n_samples]}
    rec = ModelLedger.start(shipped_checkpoint()).accept(paths[-1])
    assert rec.fast == meta["fast_step"] and rec.task is None and rec.version == 1
    assert ModelRecord.from_json(rec.to_json()) == rec
    wait = UpdateWait("/model_learner_node")
    wait.add_record(rec)
    assert wait.outcome(1) is None  # a fast model is not the update after task 1

    ended = InPeel(FastStepper(prior, CFG), tmp_path / "ended", "/model_learner_node")
    snapshots = feed(ended, peel, 0, len(peel))
    ended.end_task(0)
    assert all(ended.step(d)[1] is None for d in snapshots)  # stepped, never written
    assert not (tmp_path / "ended").exists() or not list((tmp_path / "ended").iterdir())
    assert feed(ended, peel, 0, 40) == []  # a late sample of the ended task starts nothing


def test_the_experiment_arm_plans_on_its_fast_models_and_records_them(tmp_path: Path) -> None:
    """``peel experiment``'s ``ol-mppi-fast`` arm (run_job, the shipped model, two short peels
    of the level-3 plant, small N/H): each task's record holds its fast steps with their
    identity, the errors of the model in use and of the pretrained model per sample, and the
    second task's model came from the update between the peels (the prior, not a fast model)."""
    from peel_experiments.experiment import Setup, planner_params, run_job

    sim = tmp_path / "sim.yaml"
    sim.write_text("peel_sim_node:\n  ros__parameters:\n    task:\n      t_max_s: 8.0\n")
    learner = tmp_path / "learner.yaml"
    learner.write_text("model_learner_node:\n  ros__parameters:\n    maml:\n      meta_steps: 1\n"
                       "      support_slices: 4\n      query_slices: 4\n      eval_slices: 4\n")
    setup = Setup(checkpoint=str(shipped_checkpoint()), tasks=2, sim_overrides=str(sim),
                  planner_params=planner_params(n_samples=8, horizon=2),
                  learner_overrides=str(learner), save_model=False, plant_level=3)
    out = run_job("ol-mppi-fast", 801, setup)
    first, second = out["tasks"]
    assert first["update"]["updated"] and second["model_version"] == 1  # the update after 1
    for rec in (first, second):
        fast = rec["fast"]
        assert fast["steps"] == len(fast["results"]) == len(fast["fast_s"]) >= 1
        assert fast["accepted"] == len(fast["identities"])
        assert len(fast["error_in_use_n"]) == len(fast["error_pretrained_n"]) == rec["n_samples"] - 1
        for r in fast["results"]:
            assert r["task"] == rec["task"] and r["fit_end"] == r["n_samples"] - CFG.fast_holdout
    # task 1 plans on the pretrained model until its first used fast step
    e_use, e_pre = (np.asarray(first["fast"][k]) for k in ("error_in_use_n", "error_pretrained_n"))
    used = [r["n_samples"] for r in first["fast"]["results"] if r["accepted"]]
    upto = (used[0] if used else len(e_pre) + 1) - 1
    np.testing.assert_allclose(e_use[:upto], e_pre[:upto], rtol=1e-6)
