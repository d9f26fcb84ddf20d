"""The learner node's ROS-free core (:class:`model_learner_node.online.OnlineLearner`): it
refuses a starting model with non-finite outputs, reports a failed update instead of offering
its model, keeps its last good weights, and names every update it writes (producer, task)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

from peel_model.checkpoint import load_checkpoint, save_checkpoint, shipped_checkpoint
from peel_msgs_py.errors import PeelError

PRODUCER = "/model_learner_node"


class _Log:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def info(self, msg: str) -> None:
        self.lines.append(msg)

    warn = error = info


def _values(tmp: Path, **over: Any) -> dict[str, Any]:
    from model_learner_node.parameters import SPECS
    from peel_msgs_py.params import load_node_params, validate

    known = {s.name for s in SPECS}
    flat = {k: v for k, v in load_node_params("model_learner_node").items() if k in known}
    flat.update({"node.out_dir": str(tmp / "models"), "maml.meta_steps": 1,
                 "maml.support_slices": 4, "maml.query_slices": 4, "maml.eval_slices": 4})
    flat.update(over)
    return validate(SPECS, flat)


@pytest.fixture(scope="module")
def trajectory() -> Any:
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv
    from peel_sim_node.episode import run_episode

    env = PeelEnv(load_sim_config(), source="plant", seed=1)
    try:
        traj = run_episode(env, lambda _h: 3.0, seed=1)
    finally:
        env.close()
    traj.meta["task_index"] = 0
    return traj


def test_starting_model_with_non_finite_outputs_is_refused(tmp_path: Path) -> None:
    from model_learner_node.online import OnlineLearner

    pred = load_checkpoint(shipped_checkpoint())
    with torch.no_grad():
        for p in pred.parameters():
            p.mul_(1e30)
    huge = save_checkpoint(tmp_path / "huge.safetensors", pred)
    with pytest.raises(PeelError, match=r"huge\.safetensors.*non-finite forces"):
        OnlineLearner(_values(tmp_path, **{"node.init_model": str(huge)}), producer=PRODUCER)
    assert not (tmp_path / "models").exists()  # refused before anything was written


def test_failed_update_is_reported_and_the_last_good_weights_stay(tmp_path: Path,
                                                                  trajectory: Any) -> None:
    from model_learner_node.online import OnlineLearner
    from peel_model.validation import check_finite_outputs

    learner = OnlineLearner(_values(tmp_path, **{"maml.beta": 1e30}), producer=PRODUCER)
    before = {k: v.clone() for k, v in learner.predictor.state_dict().items()}
    log = _Log()
    report = learner.learn(trajectory, log)
    assert (report.status, report.task, report.producer) == ("failed", 1, PRODUCER)
    assert "non-finite" in report.reason and report.path is None
    assert any("update after task 1 failed" in line for line in log.lines), log.lines
    after = learner.predictor.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # the last good weights
    check_finite_outputs(learner.predictor)
    assert not list((tmp_path / "models").glob("model_v*.safetensors"))  # nothing offered
    assert len(learner.pool) == 1  # the measured trajectory still joins the pool


def test_update_names_its_producer_and_task(tmp_path: Path, trajectory: Any) -> None:
    from model_learner_node.online import OnlineLearner
    from peel_model.versions import ModelLedger

    learner = OnlineLearner(_values(tmp_path), producer=PRODUCER)
    report = learner.learn(trajectory, _Log())
    assert (report.status, report.task) == ("offered", 1), report
    ledger = ModelLedger.start(shipped_checkpoint())
    rec = ledger.accept(report.path)
    assert (rec.version, rec.producer, rec.task, rec.sha256) == (1, PRODUCER, 1, report.sha256)
    assert ledger.update_for(PRODUCER, 1) == rec
