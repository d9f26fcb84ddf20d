"""Online learning of the forward model by meta learning: Algorithm 1 (paper section 3.4).

One call of :meth:`MetaLearner.update` runs Algorithm 1 once, between two peels:

1. build the support set D_new from the newest trajectory tau_new (slices as in Fig. 6) and take
   ``inner_steps`` gradient steps of size alpha: theta'_new = theta - alpha grad L_{D_new}(F_theta)
   (Eq. 26);
2. pick M trajectories tau_i from the replay pool *task-oriented* (see below), build their support
   sets D_i and inner-adapted parameters theta'_i the same way (Eq. 26);
3. draw the query sets D'_new (from tau_new) and D'_i (from tau_i) independently of the support
   sets and take the meta step (Eq. 27)::

       theta <- theta - beta * grad_theta [ L_{D'_new}(F_{theta'_new}) + sum_i L_{D'_i}(F_{theta'_i}) ]

Steps 1-3 are repeated ``meta_steps`` times per update (Algorithm 1's "while not converge"), each
time with freshly drawn slices. The loss L is the model's training loss L_MSE + kappa L_PENE
(Eq. 23-25) from :mod:`model_learner_node.losses`.

The meta-gradient is computed with ``torch.func``: the model is evaluated with
``functional_call`` on a dict of parameter tensors, the inner steps use ``torch.func.grad`` and the
outer gradient is ``torch.func.grad`` of the whole meta objective, so it differentiates through the
inner steps (second order, the default). With ``first_order`` the inner gradients are detached
(FOMAML): d theta'/d theta is taken as the identity and the meta-gradient is the query-loss
gradient evaluated at theta'.

Task-oriented sampling (Algorithm 1 step 4). The paper scores the pooled trajectories with the
trajectory scoring of its ref. [34] and takes the M best. Our score (:func:`trajectory_score`) is
the task objective itself: ``score = -J(tau)``, the negated total cost J of Eq. 3 that the planner
computed when the trajectory was recorded (``traj.meta["cost"]``); a trajectory that did not reach
q_ter (outcome other than ``done``) gets an extra ``-FAILED_PENALTY`` so that every successful
peel ranks above every failed one. Higher score is better; ties keep the newer trajectory first.
A trajectory without a recorded cost is scored by its completion time (``-t_cpl``) instead.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.func import functional_call, grad

from peel_model.windows import Windows, padded_times
from peel_msgs_py.errors import PeelError
from peel_msgs_py.params import load_node_params, validate_group
from peel_msgs_py.trajectory import Trajectory

from .config import MAML_SPECS, TrainConfig, load_train_config
from .losses import mse_loss, pene_loss
from .replay import ReplayPool

#: Score handicap of a trajectory that did not complete the task (see module docstring).
FAILED_PENALTY: float = 1.0e6

@dataclass(frozen=True)
class MamlConfig:
    """The ``maml.*`` parameters (Eq. 26-27 and Algorithm 1); see :data:`MAML_SPECS`."""

    alpha: float = 1.0e-3
    beta: float = 1.0e-3
    m: int = 4
    support_slices: int = 32
    query_slices: int = 32
    slice_len: int = 0
    inner_steps: int = 1
    meta_steps: int = 20
    first_order: bool = False
    optimizer: str = "adam"
    grad_clip: float = 0.0
    task_reduce: str = "sum"
    eval_slices: int = 64
    seed: int = 0

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> MamlConfig:
        """Build from a flat parameter dict; keys outside ``maml.`` are ignored."""
        return cls(**validate_group(MAML_SPECS, flat, "maml", strip=True))


def load_maml_config(overrides: str | None = None, **changes: Any) -> MamlConfig:
    """The shipped ``maml:`` group of config/model_learner_node.yaml, plus keyword changes."""
    flat = load_node_params("model_learner_node", overrides)
    flat.update({f"maml.{k}": v for k, v in changes.items()})
    return MamlConfig.from_params(flat)


# --------------------------------------------------------------------------------------------
# task-oriented sampling (Algorithm 1 step 4)


def trajectory_score(traj: Trajectory) -> float:
    """Task-oriented score of a pooled trajectory, higher is better (module docstring).

    ``-J(tau)`` from ``traj.meta["cost"]`` (Eq. 3), or ``-t_cpl`` when no cost was recorded;
    minus :data:`FAILED_PENALTY` when the task did not end ``done``.
    """
    cost = traj.meta.get("cost") if isinstance(traj.meta, Mapping) else None
    score = -float(cost) if cost is not None and math.isfinite(float(cost)) else -traj.t_cpl
    if traj.outcome != "done":
        score -= FAILED_PENALTY
    return score


def select_task_oriented(
    trajs: Sequence[Trajectory],
    m: int,
    score_fn: Callable[[Trajectory], float] = trajectory_score,
) -> list[int]:
    """Indices of the M best trajectories by ``score_fn`` (best first; ties: newer first)."""
    if m <= 0 or not trajs:
        return []
    scored = [(float(score_fn(t)), i) for i, t in enumerate(trajs)]
    scored.sort(key=lambda si: (-si[0], -si[1]))
    return [i for _, i in scored[:m]]


def pool_trajectories(pool: Any) -> list[Trajectory]:
    """The whole trajectories held by a replay pool (or a plain sequence of trajectories)."""
    if pool is None:
        return []
    for attr in ("trajectories", "trajs"):
        held = getattr(pool, attr, None)
        if held is not None:
            return list(held() if callable(held) else held)
    if isinstance(pool, Iterable):
        return list(pool)
    raise PeelError(f"replay pool of type {type(pool).__name__} does not expose its trajectories")


# --------------------------------------------------------------------------------------------
# slices (Fig. 6) and the loss (Eq. 23-25)


def sample_batch(
    trajs: Sequence[Trajectory] | ReplayPool,
    n_slices: int,
    h: int,
    slice_len: int,
    rng: np.random.Generator,
    dtype: torch.dtype = torch.float32,
    pad_front: int | None = None,
    with_time: bool = False,
) -> Windows:
    """``n_slices`` slices (Fig. 6) from the model package's replay pool, as model windows.

    Each slice of ``slice_len`` samples starts at a random position of a random trajectory
    (:meth:`ReplayPool.sample_slices`) and yields its ``slice_len - h`` one-step windows
    (:func:`peel_model.windows.windows_from_slices`). Trajectories are front-padded
    with ``pad_front`` copies of sample 0 (default h - 1, as in offline training), so the start
    of a peel is in the data. Returns :class:`Windows` of torch tensors of ``dtype``;
    ``with_time`` adds ``t_next`` (the time of each window's sample k+1 in its task) for models
    with time terms (:class:`~peel_model.compensated.CompensatedPredictor`).
    """
    pool = trajs if isinstance(trajs, ReplayPool) else ReplayPool(
        trajs, pad_front=h - 1 if pad_front is None else pad_front)
    length = max(slice_len, h + 1)
    slices = pool.sample_slices(n_slices, length, rng)
    w = slices.windows(h)

    def conv(a: np.ndarray) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)

    t_next = None
    if with_time:
        held = pool.trajectories
        rows = np.arange(h, length)
        t_next = conv(np.concatenate([
            padded_times(held[i], pool.pad_front)[s + rows]
            for i, s in zip(slices.traj_index, slices.start, strict=True)]))
    return Windows(conv(w.hist), conv(w.v_next), conv(w.f_next), conv(w.psi_next), t_next)


def default_loss(pred: Tensor, batch: Windows) -> Tensor:
    """Plain mean squared force error (Eq. 23 without scaling); for models without buffers."""
    return ((pred - batch.f_next) ** 2).mean()


def model_loss_fn(
    predictor: torch.nn.Module, train_cfg: TrainConfig | None = None
) -> Callable[[Tensor, Windows], Tensor]:
    """The model's training loss L_MSE + kappa L_PENE (Eq. 23-25) as ``loss(pred, windows)``.

    Same terms as :func:`model_learner_node.losses.total_loss` (channel scaling by the
    predictor's ``out_std``, psi from :meth:`ForcePredictor.psi_from_force`), but on a
    prediction made with ``functional_call`` so that it can be differentiated w.r.t. a
    parameter dict. ``kappa`` and ``psi_lim`` come from the ``train:`` group.
    """
    cfg = train_cfg or load_train_config()
    scale = getattr(predictor, "out_std", None)
    psi_fn = getattr(predictor, "psi_from_force", None)

    def loss(pred: Tensor, batch: Windows) -> Tensor:
        total = mse_loss(pred, batch.f_next, scale)
        if psi_fn is not None and cfg.kappa > 0:
            total = total + cfg.kappa * pene_loss(psi_fn(pred[:, 1]), cfg.psi_lim_mm)
        return total

    return loss


# --------------------------------------------------------------------------------------------
# Algorithm 1


Params = dict[str, Tensor]
Task = tuple[Windows, Windows]


class MetaLearner:
    """Algorithm 1 on a forward model ``predictor`` (a ``torch.nn.Module`` with ``.h``).

    ``update(new_traj, pool)`` changes ``predictor``'s parameters in place and returns a report.
    ``loss_fn(pred, batch)`` defaults to the model's training loss; ``score_fn`` to
    :func:`trajectory_score`.
    """

    def __init__(
        self,
        predictor: torch.nn.Module,
        cfg: MamlConfig | None = None,
        *,
        loss_fn: Callable[[Tensor, Windows], Tensor] | None = None,
        score_fn: Callable[[Trajectory], float] = trajectory_score,
        train_cfg: TrainConfig | None = None,
    ) -> None:
        self.model = predictor
        self.cfg = cfg or MamlConfig()
        self.loss_fn = loss_fn or model_loss_fn(predictor, train_cfg)
        self.score_fn = score_fn
        self.h = int(getattr(predictor, "h", 1))
        self.slice_len = self.cfg.slice_len or self.h + 1
        if self.slice_len <= self.h:
            raise PeelError(
                f"maml.slice_len = {self.slice_len} must exceed the model history h = {self.h}"
            )
        self.pad_front = self.h - 1
        self.version = 0
        self.n_updates = 0
        self._opt: torch.optim.Optimizer | None = None
        self._pools: dict[int, tuple[Trajectory, ReplayPool]] = {}

    # -- functional pieces -------------------------------------------------------------------

    @property
    def dtype(self) -> torch.dtype:
        return next(self.model.parameters()).dtype

    def params(self) -> Params:
        """The trainable parameters theta as a dict of detached tensors."""
        return {k: p.detach() for k, p in self.model.named_parameters() if p.requires_grad}

    def loss(self, params: Params, batch: Windows) -> Tensor:
        """L_D(F_theta) of Eq. 26-27 evaluated with ``functional_call`` at ``params``."""
        pred = functional_call(self.model, params, (batch.hist, batch.v_next),
                               batch.model_kwargs(self.model), strict=False)
        return self.loss_fn(pred, batch)

    def adapt(self, params: Params, support: Windows) -> Params:
        """Eq. 26: theta' = theta - alpha grad L_support, ``inner_steps`` times."""
        p = params
        for _ in range(self.cfg.inner_steps):
            g = grad(self.loss)(p, support)
            if self.cfg.first_order:
                g = {k: v.detach() for k, v in g.items()}
            p = {k: p[k] - self.cfg.alpha * g[k] for k in p}
        return p

    def meta_objective(self, params: Params, tasks: Sequence[Task]) -> Tensor:
        """The bracket of Eq. 27: sum over tasks of L_query(F_{theta'}), theta' from Eq. 26.

        With ``task_reduce = "mean"`` the sum is divided by the number of tasks (1 + M, fewer
        while the pool is short), so the meta step no longer grows with the number of tasks.
        """
        total = params[next(iter(params))].new_zeros(())
        for support, query in tasks:
            total = total + self.loss(self.adapt(params, support), query)
        if self.cfg.task_reduce == "mean" and tasks:
            total = total / len(tasks)
        return total

    def meta_gradient(self, params: Params, tasks: Sequence[Task]) -> Params:
        """grad_theta of :meth:`meta_objective` (second order unless ``first_order``)."""
        return grad(self.meta_objective)(params, tasks)

    # -- Algorithm 1 -------------------------------------------------------------------------

    def _rng(self, salt: int) -> np.random.Generator:
        return np.random.default_rng([self.cfg.seed, self.n_updates, salt])

    def _pool(self, traj: Trajectory) -> ReplayPool:
        """A one-trajectory replay pool (cached per trajectory object)."""
        key = id(traj)
        hit = self._pools.get(key)
        if hit is None or hit[0] is not traj:
            hit = (traj, ReplayPool([traj], pad_front=self.pad_front))
            self._pools[key] = hit
        return hit[1]

    def _batch(self, traj: Trajectory, n: int, rng: np.random.Generator) -> Windows:
        return sample_batch(self._pool(traj), n, self.h, self.slice_len, rng, self.dtype,
                            with_time=bool(getattr(self.model, "needs_time", False)))

    def usable(self, traj: Trajectory) -> bool:
        """Whether ``traj`` is long enough for one slice."""
        return len(traj) + self.pad_front >= self.slice_len

    def draw_tasks(
        self, new_traj: Trajectory, chosen: Sequence[Trajectory], rng: np.random.Generator
    ) -> list[Task]:
        """Support and query sets (drawn independently) for tau_new and each chosen tau_i."""
        tasks = []
        for traj in [new_traj, *chosen]:
            support = self._batch(traj, self.cfg.support_slices, rng)
            query = self._batch(traj, self.cfg.query_slices, rng)
            tasks.append((support, query))
        return tasks

    def _apply(self, g: Params) -> float:
        norm = float(torch.sqrt(sum((v.double() ** 2).sum() for v in g.values())))
        scale = 1.0
        if self.cfg.grad_clip > 0 and norm > self.cfg.grad_clip:
            scale = self.cfg.grad_clip / (norm + 1e-12)
        named = dict(self.model.named_parameters())
        with torch.no_grad():
            if self.cfg.optimizer == "adam":
                if self._opt is None:
                    self._opt = self._adam()
                for k, v in g.items():
                    named[k].grad = (v * scale).to(named[k].dtype)
                self._opt.step()
                for k in g:
                    named[k].grad = None
            else:
                for k, v in g.items():
                    named[k].sub_(self.cfg.beta * scale * v)
        return norm

    def _adam(self) -> torch.optim.Optimizer:
        """The meta-optimiser of Eq. 27 (learning rate beta) over theta, in :meth:`params` order."""
        named = dict(self.model.named_parameters())
        return torch.optim.Adam([named[k] for k in self.params()], lr=self.cfg.beta)

    def state(self) -> dict[str, Any]:
        """A copy of theta and of the meta-optimiser's state; :meth:`restore` brings them back
        (the learner node undoes an update whose model predicts non-finite forces; a restarted
        learner goes on from its saved state, :mod:`~model_learner_node.resume`)."""
        return {"model": copy.deepcopy(self.model.state_dict()),
                "opt": copy.deepcopy(self._opt.state_dict()) if self._opt is not None else None,
                "n_updates": self.n_updates, "version": self.version}

    def restore(self, state: Mapping[str, Any]) -> None:
        """Back to a :meth:`state` taken earlier."""
        self.model.load_state_dict(state["model"])
        if state["opt"] is None:
            self._opt = None
        else:
            if self._opt is None:
                self._opt = self._adam()
            self._opt.load_state_dict(state["opt"])
        self.n_updates, self.version = state["n_updates"], state["version"]
        self._pools.clear()

    def update(self, new_traj: Trajectory, pool: Any = None) -> dict[str, Any]:
        """Run Algorithm 1 once with the newest trajectory and the replay pool.

        ``pool`` holds the earlier trajectories (a ReplayPool or a sequence); ``new_traj`` is
        excluded from the M candidates if it is already in it. Returns a JSON-able report with
        the query loss of tau_new before and after, the chosen pool indices, the meta-gradient
        norms and ``update_s`` (wall time of the update).
        """
        t0 = time.perf_counter()
        if not self.usable(new_traj):
            return {"updated": False, "reason": f"tau_new has {len(new_traj)} samples, "
                    f"a slice needs {self.slice_len}", "version": self.version,
                    "update_s": time.perf_counter() - t0}
        candidates = [t for t in pool_trajectories(pool)
                      if t is not new_traj and self.usable(t)]
        chosen_idx = select_task_oriented(candidates, self.cfg.m, self.score_fn)
        chosen = [candidates[i] for i in chosen_idx]
        was_training = self.model.training
        self.model.eval()  # deterministic forward passes (no dropout) inside torch.func
        try:
            eval_batch = self._batch(new_traj, self.cfg.eval_slices, self._rng(1))
            with torch.no_grad():
                before = float(self.loss(self.params(), eval_batch))
            rng = self._rng(2)
            norms = []
            for _ in range(self.cfg.meta_steps):
                tasks = self.draw_tasks(new_traj, chosen, rng)
                g = self.meta_gradient(self.params(), tasks)
                if not all(torch.isfinite(v).all() for v in g.values()):
                    raise PeelError("maml: non-finite meta-gradient; lower maml.alpha/beta")
                norms.append(self._apply(g))
            with torch.no_grad():
                after = float(self.loss(self.params(), eval_batch))
        finally:
            self.model.train(was_training)
        self.n_updates += 1
        self.version += 1
        self._pools.clear()
        return {
            "updated": True,
            "version": self.version,
            "query_loss_before": before,
            "query_loss_after": after,
            "chosen": [int(i) for i in chosen_idx],
            "chosen_scores": [float(self.score_fn(t)) for t in chosen],
            "grad_norms": norms,
            "meta_steps": self.cfg.meta_steps,
            "first_order": self.cfg.first_order,
            "update_s": time.perf_counter() - t0,
        }
