"""A model earns its swap: the held-out check of an update before the planner gets it.

Algorithm 1 (3.4) fits the meta-parameters on the newest peel tau_new and on M peels of the
replay pool; nothing in it asks whether the result predicts the plant better than the model the
planner is using. :class:`HeldOutGate` wraps an updater (:class:`~model_learner_node.maml.
MetaLearner` or :class:`~model_learner_node.baselines2.HistoryRetrainer`) and asks it:

1. the last ``holdout`` fraction of tau_new's samples (its end, contiguous in time) is kept out
   of the update: the updater sees ``tau_new[:c]`` with ``c = ceil((1 - holdout) T)``;
2. the one-step force error of Eq. 39 over both channels,
   ``e(theta) = sqrt(mean_k ||F_{k+1} - f_theta(x_k, v_{k+1})||^2)``, is taken on the held-out
   samples (targets k + 1 >= c; their history may reach back before c, it is input only) with
   the weights in use (before the update) and with the updated ones;
3. the update is offered when ``e(theta_new) <= (1 + tolerance) e(theta_in_use)``; otherwise the
   updater is put back on the weights in use (so its next update starts from them) and the
   report says ``updated: False`` with the two errors: the planner keeps its model.

The replay pool still gets the whole of tau_new (the caller adds it), so the next update fits
the samples held out here. A peel too short to hold out ``min_samples`` targets is updated on
whole and reported as not checked, and so is a corrected model whose effect terms need the
samples' times (docs/residual.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from peel_model.windows import Windows, trajectory_windows
from peel_msgs_py.params import load_node_params, validate_group
from peel_msgs_py.trajectory import Trajectory

from .config import GATE_SPECS
from .metrics import predict_windows


@dataclass(frozen=True)
class GateConfig:
    """The ``gate.*`` parameters (module docstring)."""

    holdout: float = 0.0
    tolerance: float = 0.0
    min_samples: int = 10

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> GateConfig:
        """Build from a flat parameter dict; keys outside ``gate.`` are ignored."""
        return cls(**validate_group(GATE_SPECS, flat, "gate", strip=True))


def load_gate_config(overrides: str | None = None, **changes: Any) -> GateConfig:
    """The shipped ``gate:`` group of config/model_learner_node.yaml, plus keyword changes."""
    flat = load_node_params("model_learner_node", overrides)
    flat.update({f"gate.{k}": v for k, v in changes.items()})
    return GateConfig.from_params(flat)


def cut_index(n: int, holdout: float) -> int:
    """``c = ceil((1 - holdout) n)``: the first held-out sample of an ``n``-sample peel."""
    return min(n, math.ceil((1.0 - holdout) * n - 1e-9))


def held_out_windows(traj: Trajectory, h: int, cut: int) -> Windows:
    """The windows of ``traj`` whose target sample k + 1 is at or after ``cut``."""
    win = trajectory_windows(traj, h)
    idx = np.flatnonzero(np.arange(len(win)) + 1 >= cut)
    return win.subset(idx)


def one_step_error(predictor: Any, win: Windows) -> float:
    """Eq. 39 over both force channels: RMS of ``F_{k+1} - f_theta`` on ``win`` (N)."""
    was_training = predictor.training
    predictor.eval()
    try:
        pred = predict_windows(predictor, win)
    finally:
        predictor.train(was_training)
    return float(np.sqrt(np.mean((win.f_next - pred) ** 2)))


class HeldOutGate:
    """``update(tau_new, pool)`` of the wrapped updater, offered only when it earns it."""

    def __init__(self, updater: Any, predictor: Any, cfg: GateConfig) -> None:
        self.updater, self.predictor, self.cfg = updater, predictor, cfg

    def state(self) -> dict[str, Any]:
        return self.updater.state()

    def restore(self, state: Mapping[str, Any]) -> None:
        self.updater.restore(state)

    def update(self, new_traj: Trajectory, pool: Any = None) -> dict[str, Any]:
        """The wrapped update on tau_new's head, checked on its held-out tail (module doc)."""
        n = len(new_traj)
        cut = cut_index(n, self.cfg.holdout)
        if (self.cfg.holdout <= 0.0 or n - cut < self.cfg.min_samples
                or getattr(self.predictor, "needs_time", False)):  # effect terms in time: as is
            report = self.updater.update(new_traj, pool)
            return {**report, "gate": {"checked": False, "holdout_samples": n - cut}}
        held = held_out_windows(new_traj, self.predictor.h, cut)
        in_use = one_step_error(self.predictor, held)
        saved = self.updater.state()
        report = self.updater.update(new_traj.slice(0, cut), pool)
        if not report.get("updated", True):
            return {**report, "gate": {"checked": False, "holdout_samples": n - cut}}
        new = one_step_error(self.predictor, held)
        earned = math.isfinite(new) and new <= (1.0 + self.cfg.tolerance) * in_use
        gate = {"checked": True, "earned": earned, "holdout_samples": n - cut,
                "error_in_use_n": in_use, "error_update_n": new}
        if earned:
            return {**report, "gate": gate}
        self.updater.restore(saved)
        return {**report, "updated": False, "version": saved.get("version"), "gate": gate,
                "reason": f"held-out check: the update predicts the newest peel's last "
                          f"{n - cut} samples worse than the model in use (one-step error "
                          f"{new:.3f} N against {in_use:.3f} N); not offered"}
