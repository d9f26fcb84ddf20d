"""Typed configuration of the forward model's offline training (3.3, Eq. 23-25) and the groups
of the online learner: MAML (Eq. 26-27), the held-out gate and baseline 2 (4.4).

The values live in ``config/model_learner_node.yaml`` (groups ``train.*``, ``maml.*``, ``gate.*``,
``baseline2.*``); the model's own ``model.*`` group is :mod:`peel_model.config`. Every value is
checked by :func:`peel_msgs_py.params.validate` against the specs below, whose defaults mirror
the shipped YAML.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

from peel_model.config import load_params
from peel_msgs_py.params import ParamSpec, validate_group

TRAIN_SPECS: list[ParamSpec] = [
    ParamSpec("train.lr", float, 1e-4, "Adam learning rate (4.3)", min=1e-8, max=1.0),
    ParamSpec("train.kappa", float, 1.0, "L_PENE weight (Eq. 25)", min=0.0),
    ParamSpec("train.psi_lim_mm", float, 0.3, "psi_lim (Eq. 24), mm", min=0.0),
    ParamSpec("train.pad_compliance_mm_per_n", float, 0.02, "fallback psi/F_RZ, mm/N", min=0.0),
    ParamSpec("train.batch_size", int, 256, "slices per batch (3.3.1)", min=1),
    ParamSpec("train.slice_len", int, 11, "slice length, samples (3.3.1)", min=2),
    ParamSpec("train.epochs", int, 60, "maximum epochs", min=1),
    ParamSpec("train.samples_per_epoch", int, 0, "slices per epoch (0 = #windows)", min=0),
    ParamSpec("train.patience", int, 10, "early-stopping patience, epochs", min=1),
    ParamSpec("train.weight_decay", float, 0.0, "Adam weight decay", min=0.0),
    ParamSpec("train.grad_clip", float, 1.0, "gradient-norm clip (0 = off)", min=0.0),
    ParamSpec("train.seed", int, 0, "training seed", min=0),
]


#: Parameters of the ``maml:`` group of config/model_learner_node.yaml (Eq. 26-27).
MAML_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("maml.alpha", float, 1.0e-3, "inner step size alpha (Eq. 26)", min=0.0),
    ParamSpec("maml.beta", float, 1.0e-3, "meta step size beta (Eq. 27)", min=0.0),
    ParamSpec("maml.m", int, 4, "M trajectories from the replay pool (Algorithm 1 step 4)", min=0),
    ParamSpec("maml.support_slices", int, 32, "slices per support set D_new, D_i", min=1),
    ParamSpec("maml.query_slices", int, 32, "slices per query set D'_new, D'_i", min=1),
    ParamSpec("maml.slice_len", int, 0,
              "samples per slice (Fig. 6); 0 = the model's history h + 1", min=0),
    ParamSpec("maml.inner_steps", int, 1, "gradient steps of Eq. 26 per task", min=1),
    ParamSpec("maml.meta_steps", int, 20, "meta steps (Eq. 27) per update", min=1),
    ParamSpec("maml.first_order", bool, False, "drop second-order terms (FOMAML)"),
    ParamSpec("maml.optimizer", str, "adam", "meta step rule: sgd = Eq. 27, adam = Adam(beta)",
              choices=("sgd", "adam")),
    ParamSpec("maml.grad_clip", float, 0.0, "clip the meta-gradient norm; 0 = off", min=0.0),
    ParamSpec("maml.task_reduce", str, "sum",
              "Eq. 27 bracket over the 1 + M tasks: sum (paper) or mean", choices=("sum", "mean")),
    ParamSpec("maml.eval_slices", int, 64,
              "slices of tau_new for the before/after loss report", min=1),
    ParamSpec("maml.seed", int, 0, "seed of the slice sampling", min=0),
)


#: Parameters of the ``gate:`` group: the held-out check of each update before it is offered
#: (model_learner_node.gate; not in the paper, docs/model.md "A model earns its swap").
GATE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("gate.holdout", float, 0.0,
              "fraction of the newest peel's samples (its end) kept out of the update and used "
              "to check it; 0 = offer every update unchecked (the paper's Algorithm 1)",
              min=0.0, max=0.9),
    ParamSpec("gate.tolerance", float, 0.0,
              "offer when the update's one-step error (Eq. 39) on the held-out samples is at "
              "most (1 + tolerance) x the model in use's", min=0.0, max=1.0),
    ParamSpec("gate.min_samples", int, 10,
              "fewest held-out samples for a check; a shorter peel is updated on whole, unchecked",
              min=1),
)


#: Parameters of the ``online:`` group: the fast step inside the peel
#: (model_learner_node.fast_step; Eq. 26 on the running task's own samples).
ONLINE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("online.fast_every", int, 0,
              "samples of the running task between two fast steps; 0 = no fast step (the "
              "paper's Algorithm 1, between peels only)", min=0, max=1000),
    ParamSpec("online.fast_steps", int, 20, "gradient steps of Eq. 26 per fast step", min=1,
              max=100),
    ParamSpec("online.fast_alpha", float, 0.1, "step size of the fast step's Eq. 26",
              min=0.0, max=1.0),
    ParamSpec("online.fast_holdout", int, 10,
              "newest samples of the task kept out of the fit and used to check it", min=1,
              max=1000),
    ParamSpec("online.fast_min_samples", int, 20,
              "fewest fitted samples before the first fast step of a task", min=1, max=10000),
    ParamSpec("online.fast_margin", float, 0.05,
              "use the fast model when its held-out error (Eq. 39) is below (1 - margin) x "
              "the model in use's", min=0.0, max=0.9),
    ParamSpec("online.fast_params", str, "head",
              "what the fast step moves: head = the output layer's weight and bias, all = every "
              "trainable parameter", choices=("head", "all")),
    ParamSpec("online.fast_grad_clip", float, 1.0,
              "gradient norm a fast step's gradient is scaled down to; 0 = no clip", min=0.0,
              max=1000.0),
)


#: Parameters of the ``baseline2:`` group of config/model_learner_node.yaml (section 4.4).
BASELINE2_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("baseline2.steps", int, 20, "Adam steps per update", min=1),
    ParamSpec("baseline2.lr", float, 1.0e-3, "Adam learning rate", min=0.0),
    ParamSpec("baseline2.batch_slices", int, 64, "slices per mini-batch", min=1),
    ParamSpec("baseline2.slice_len", int, 0, "samples per slice; 0 = model h + 1", min=0),
    ParamSpec("baseline2.grad_clip", float, 1.0, "gradient-norm clip; 0 = off", min=0.0),
    ParamSpec("baseline2.seed", int, 0, "seed of the slice sampling", min=0),
)


@dataclass(frozen=True)
class TrainConfig:
    """Offline-learning hyper-parameters (3.3, Eq. 23-25)."""

    lr: float = 1e-4
    kappa: float = 1.0
    psi_lim_mm: float = 0.3
    pad_compliance_mm_per_n: float = 0.02
    batch_size: int = 256
    slice_len: int = 11
    epochs: int = 60
    samples_per_epoch: int = 0
    patience: int = 10
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    seed: int = 0

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> TrainConfig:
        """Validate the ``train.*`` entries of a flat parameter dict."""
        return cls(**validate_group(TRAIN_SPECS, flat, "train", strip=True))

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def load_train_config(overrides: str | None = None) -> TrainConfig:
    """:class:`TrainConfig` from ``config/model_learner_node.yaml``."""
    return TrainConfig.from_params(load_params(overrides))
