"""ROS-free model checks the planner and learner nodes share: finite outputs on a probe batch,
and model versions that stay unique and monotonic whoever swaps a model in."""

from __future__ import annotations

import pytest
import torch

from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_model.validation import check_finite_outputs
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
    from peel_model.checkpoint import save_checkpoint
    from peel_model.versions import ModelLedger, ModelRecord, update_meta

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


def test_update_wait_goes_by_identity_never_by_number() -> None:
    """The simulator's and the launcher's wait for the learner's update after task k: an
    outside model, another producer's report or the learner's own word without the planner's
    record do not end it; the planner's record of the update or a failure report do."""
    from peel_msgs_py.modelinfo import FAILED, SWAPPED, ModelRecord, UpdateReport, UpdateWait

    learner = "/model_learner_node"
    wait = UpdateWait(learner)
    wait.add_record(ModelRecord(0, "a" * 64, "/m/init.safetensors"))
    assert wait.outcome(1) is None
    wait.add_record(ModelRecord(1, "b" * 64, "/m/tuned_by_hand.safetensors"))  # outside
    wait.add_report(UpdateReport("/another_learner", 1, FAILED, "boom"))
    wait.add_report(UpdateReport(learner, 1, SWAPPED, sha256="c" * 64))  # record still on its way
    assert wait.outcome(1) is None
    wait.add_record(ModelRecord(2, "c" * 64, "/m/model_v0001.safetensors", learner, 1))
    done = wait.outcome(1)
    assert done is not None and (done.status, done.version, done.failed) == (SWAPPED, 2, False)
    wait.add_report(UpdateReport(learner, 2, FAILED, "probe batch: non-finite forces"))
    failed = wait.outcome(2)
    assert failed is not None and failed.failed and failed.version is None
    assert "non-finite" in failed.reason and wait.latest is not None and wait.latest.version == 2
    assert UpdateReport.from_json(failed.to_json()) == failed
    assert ModelRecord.from_json(wait.latest.to_json()) == wait.latest
