"""ROS-free model checks the planner and learner nodes share: finite outputs on a probe batch,
and model versions that stay unique and monotonic whoever swaps a model in."""

from __future__ import annotations

import pytest
import torch

from model_learner_node.checkpoint import load_checkpoint, shipped_checkpoint
from model_learner_node.validation import check_finite_outputs
from peel_msgs_py.errors import PeelError


def test_finite_output_probe() -> None:
    pred = load_checkpoint(shipped_checkpoint())
    check_finite_outputs(pred)
    check_finite_outputs(pred, rows=torch.randn(30, 4).abs().numpy())
    with torch.no_grad():
        for p in pred.parameters():
            p.mul_(1e30)
    assert all(bool(torch.isfinite(p).all()) for p in pred.parameters())  # weights finite
    with pytest.raises(PeelError, match="non-finite forces"):
        check_finite_outputs(pred)


def test_model_versions_unique_and_monotonic_whoever_swaps(tmp_path) -> None:
    """An outside model with an unversioned name, then the learner's own v1: no collision, and
    the learner's update is found by its identity, not by a number."""
    from model_learner_node.checkpoint import save_checkpoint
    from model_learner_node.versions import ModelLedger, ModelRecord, update_meta

    pred = load_checkpoint(shipped_checkpoint())
    ledger = ModelLedger.start(shipped_checkpoint())
    outside = save_checkpoint(tmp_path / "tuned_by_hand.safetensors", pred, {"note": "manual"})
    with torch.no_grad():
        next(pred.parameters()).add_(1e-3)
    own = save_checkpoint(tmp_path / "model_v0001.safetensors", pred,
                          update_meta("model_learner_node", 1))
    assert ledger.update_for("model_learner_node", 1) is None
    a = ledger.accept(outside)
    assert ledger.update_for("model_learner_node", 1) is None  # the outside model is not it
    b = ledger.accept(own)
    assert [r.version for r in ledger.records] == [0, 1, 2]
    assert (a.producer, b.producer, b.task) == (None, "model_learner_node", 1)
    assert ledger.update_for("model_learner_node", 1) == b and b.sha256 != a.sha256
    assert ModelRecord.from_json(b.to_json()) == b
