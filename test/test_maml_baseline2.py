"""Baseline 2 (4.4): every update retrains on all history so far."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_maml_algorithm import H, TinyModel, make_traj

from model_learner_node.baselines2 import Baseline2Config, HistoryRetrainer, load_baseline2_config
from model_learner_node.maml import default_loss, sample_batch
from peel_msgs_py.errors import ParameterError


def _loss_on(model: torch.nn.Module, trajs: list) -> float:
    w = sample_batch(trajs, 64, H, H + 1, np.random.default_rng(0))
    with torch.no_grad():
        return float(default_loss(model(w.hist, w.v_next), w))


def test_retraining_uses_all_history_and_lowers_its_loss() -> None:
    torch.manual_seed(0)
    model = TinyModel()
    retrainer = HistoryRetrainer(model, Baseline2Config(steps=40, lr=0.01, batch_slices=32,
                                                        slice_len=H + 2), loss_fn=default_loss)
    history = [make_traj(i, gain=1.5) for i in range(3)]
    new = make_traj(9, gain=1.5)
    before = _loss_on(model, [*history, new])
    rep = retrainer.update(new, history)
    assert rep["updated"] and rep["version"] == 1 and rep["n_history"] == 4
    assert _loss_on(model, [*history, new]) < 0.5 * before
    rep2 = retrainer.update(make_traj(10), [*history, new])
    assert rep2["n_history"] == 5 and rep2["version"] == 2


def test_baseline2_is_deterministic_and_config_is_validated() -> None:
    params = []
    for _ in range(2):
        torch.manual_seed(1)
        model = TinyModel()
        HistoryRetrainer(model, Baseline2Config(steps=3, seed=4), loss_fn=default_loss).update(
            make_traj(1), [make_traj(2)])
        params.append([p.detach().clone() for p in model.parameters()])
    for a, b in zip(*params, strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ParameterError, match=r"baseline2\.steps"):
        Baseline2Config.from_params({"baseline2.steps": 0})
    assert load_baseline2_config().steps >= 1
