"""Baseline 2 of section 4.4: every update retrains the model on all history so far.

The paper compares OL-MPPI with "Baseline 2: compared with OL-MPPI, each update of the system
model uses all previous historical experience" (4.4) and attributes its fluctuating cost to
catastrophic forgetting (3.4: "the new samples have a smaller proportion in the dataset, and the
latest features of the system model are difficult to incorporate").

:class:`HistoryRetrainer` implements it as plain supervised fine-tuning: starting from the current
weights, ``steps`` Adam steps (learning rate ``lr``, a fresh optimizer per update) on mini-batches
of ``batch_slices`` slices (Fig. 6) drawn uniformly from *every* trajectory recorded so far
(the replay pool plus the newest one), minimising the model's training loss
L_MSE + kappa L_PENE (Eq. 25). So the newest peel has weight 1/n among n peels, unlike
Algorithm 1 which always includes it (:mod:`model_learner_node.maml`). Baseline 1 is the model
never updated and needs no code.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from peel_model.windows import Windows
from peel_msgs_py.params import load_node_params, validate_group
from peel_msgs_py.trajectory import Trajectory

from .config import BASELINE2_SPECS, TrainConfig
from .maml import model_loss_fn, pool_trajectories, sample_batch
from .replay import ReplayPool


@dataclass(frozen=True)
class Baseline2Config:
    """The ``baseline2.*`` parameters; see :data:`BASELINE2_SPECS`."""

    steps: int = 20
    lr: float = 1.0e-3
    batch_slices: int = 64
    slice_len: int = 0
    grad_clip: float = 1.0
    seed: int = 0

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> Baseline2Config:
        """Build from a flat parameter dict; keys outside ``baseline2.`` are ignored."""
        return cls(**validate_group(BASELINE2_SPECS, flat, "baseline2", strip=True))


def load_baseline2_config(overrides: str | None = None, **changes: Any) -> Baseline2Config:
    """The shipped ``baseline2:`` group of config/model_learner_node.yaml, plus changes."""
    flat = load_node_params("model_learner_node", overrides)
    flat.update({f"baseline2.{k}": v for k, v in changes.items()})
    return Baseline2Config.from_params(flat)


class HistoryRetrainer:
    """Baseline 2: ``update(new_traj, pool)`` fine-tunes ``predictor`` on all history so far."""

    def __init__(
        self,
        predictor: torch.nn.Module,
        cfg: Baseline2Config | None = None,
        *,
        loss_fn: Callable[[Tensor, Windows], Tensor] | None = None,
        train_cfg: TrainConfig | None = None,
    ) -> None:
        self.model = predictor
        self.cfg = cfg or Baseline2Config()
        self.loss_fn = loss_fn or model_loss_fn(predictor, train_cfg)
        self.h = int(getattr(predictor, "h", 1))
        self.slice_len = max(self.cfg.slice_len, self.h + 1)
        self.version = 0
        self.n_updates = 0

    def state(self) -> dict[str, Any]:
        """A copy of the weights (each update starts a fresh optimiser); see :meth:`restore`."""
        return {"model": copy.deepcopy(self.model.state_dict()), "n_updates": self.n_updates,
                "version": self.version}

    def restore(self, state: Mapping[str, Any]) -> None:
        """Back to a :meth:`state` taken earlier."""
        self.model.load_state_dict(state["model"])
        self.n_updates, self.version = state["n_updates"], state["version"]

    def _loss(self, batch: Windows) -> Tensor:
        return self.loss_fn(self.model(batch.hist, batch.v_next, **batch.model_kwargs(self.model)),
                            batch)

    def update(self, new_traj: Trajectory, pool: Any = None) -> dict[str, Any]:
        """Retrain on the pool's trajectories plus ``new_traj``; returns a JSON-able report."""
        t0 = time.perf_counter()
        history = [t for t in pool_trajectories(pool) if t is not new_traj]
        history.append(new_traj)
        pad = self.h - 1  # front padding as in offline training (peel_model.windows)
        history = [t for t in history if len(t) + pad >= self.slice_len]
        if not history:
            return {"updated": False, "reason": "no trajectory long enough for a slice",
                    "version": self.version, "update_s": time.perf_counter() - t0}
        replay = ReplayPool(history, pad_front=pad)
        rng = np.random.default_rng([self.cfg.seed, self.n_updates])
        dtype = next(self.model.parameters()).dtype
        was_training = self.model.training
        self.model.train()
        opt = torch.optim.Adam([p for p in self.model.parameters() if p.requires_grad],
                               lr=self.cfg.lr)
        losses = []
        try:
            for _ in range(self.cfg.steps):
                batch = sample_batch(replay, self.cfg.batch_slices, self.h, self.slice_len,
                                     rng, dtype,
                                     with_time=bool(getattr(self.model, "needs_time", False)))
                opt.zero_grad(set_to_none=True)
                loss = self._loss(batch)
                loss.backward()
                if self.cfg.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
                opt.step()
                losses.append(float(loss.detach()))
        finally:
            self.model.train(was_training)
        self.n_updates += 1
        self.version += 1
        return {
            "updated": True,
            "version": self.version,
            "n_history": len(history),
            "loss_first": losses[0],
            "loss_last": losses[-1],
            "steps": self.cfg.steps,
            "update_s": time.perf_counter() - t0,
        }
