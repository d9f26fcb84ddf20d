"""Adaptation inside the peel: the fast step of the meta-learned prior on the running task.

Algorithm 1 (3.4) meta-learns theta so that a few gradient steps of Eq. 26 on a task's own data
adapt the model to that task. Between peels (:mod:`model_learner_node.maml`) those steps are only
part of the meta objective; the fast step takes them *during* the peel, on the samples of the
running task tau_run recorded so far (Nagabandi et al. 2019 adapt within an episode the same way):

1. every ``online.fast_every`` samples, with n samples of tau_run recorded, the newest
   ``online.fast_holdout`` targets are held out; the fit set D_run is every one-step window of
   tau_run whose target k + 1 lies before the cut c = n - holdout;
2. ``online.fast_steps`` plain steps of Eq. 26 from the prior theta (never from an earlier fast
   model): theta' <- theta' - alpha_fast grad L_{D_run}(F_theta'), L the model's training loss
   L_MSE + kappa L_PENE (Eq. 23-25), full batch; with ``online.fast_params: head`` only the
   output layer (the model's last weight and bias) moves, the features stay the prior's; a
   gradient longer than ``online.fast_grad_clip`` is scaled to that length (the step of a
   large error would otherwise leave the region where the loss is near quadratic);
3. the one-step force error of Eq. 39 over both channels, ``e = sqrt(mean ||F_{k+1} - f||^2)``,
   is taken on the held-out targets k + 1 >= c with theta' and with the model in use (the prior
   or the last fast model accepted in this task: neither was fitted on them, the earlier fit
   stopped at an earlier cut);
4. theta' is offered for planning only when ``e(theta') < (1 - online.fast_margin) e(in use)``;
   else the model in use stays.

The fast model is a copy of the prior: theta itself is never changed here, so a fast model never
becomes the shared prior (the between-peel update still starts from theta and passes the
learner's held-out check, :mod:`model_learner_node.gate`). Each result names the fast step
(task, step number, fitted and checked samples) for the model identity of the trajectory meta.
A model whose effect terms need the samples' times (docs/residual.md) is not fast-stepped.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.func import functional_call, grad

from peel_model.windows import Windows, trajectory_windows
from peel_msgs_py.params import load_node_params, validate_group
from peel_msgs_py.trajectory import Trajectory

from .config import ONLINE_SPECS
from .gate import one_step_error
from .maml import model_loss_fn


@dataclass(frozen=True)
class FastStepConfig:
    """The ``online.*`` parameters of the fast step (module docstring); see :data:`ONLINE_SPECS`."""

    fast_every: int = 0
    fast_steps: int = 20
    fast_alpha: float = 0.1
    fast_holdout: int = 10
    fast_min_samples: int = 20
    fast_margin: float = 0.05
    fast_params: str = "head"
    fast_grad_clip: float = 1.0

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> FastStepConfig:
        """Build from a flat parameter dict; keys outside ``online.`` are ignored."""
        return cls(**validate_group(ONLINE_SPECS, flat, "online", strip=True))

    @property
    def enabled(self) -> bool:
        return self.fast_every > 0


def load_fast_config(overrides: str | None = None, **changes: Any) -> FastStepConfig:
    """The shipped ``online:`` group of config/model_learner_node.yaml, plus keyword changes."""
    flat = load_node_params("model_learner_node", overrides)
    flat.update({f"online.{k}": v for k, v in changes.items()})
    return FastStepConfig.from_params(flat)


@dataclass(frozen=True)
class FastResult:
    """One fast step: its identity (``task``, ``step``, samples fitted ``[0, fit_end)`` and
    checked ``[fit_end, n_samples)``), the three errors (N) and whether it was accepted."""

    task: int
    step: int
    n_samples: int
    fit_end: int
    error_prior_n: float
    error_in_use_n: float
    error_fast_n: float
    accepted: bool
    fast_s: float

    def identity(self) -> dict[str, Any]:
        """What the trajectory meta's model identity names of this fast step."""
        return {"task": self.task, "step": self.step, "fit_samples": [0, self.fit_end],
                "check_samples": [self.fit_end, self.n_samples]}

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class FastStepper:
    """The fast step of ``prior`` on one running task at a time (module docstring).

    ``observe(history)`` is called with the task's samples so far; every ``fast_every`` samples
    it returns a :class:`FastResult` (``model`` holds the accepted fast model, else the model in
    use stays). ``start(task)`` begins a new task on the prior.
    """

    def __init__(self, prior: torch.nn.Module, cfg: FastStepConfig,
                 loss_fn: Callable[[Tensor, Windows], Tensor] | None = None) -> None:
        self.prior, self.cfg = prior, cfg
        self.loss_fn = loss_fn or model_loss_fn(prior)
        self.h = int(getattr(prior, "h", 1))
        self.task = 0
        self.model: torch.nn.Module = prior  # the model in use in this task
        self.steps = 0
        self.results: list[FastResult] = []
        self._last_n = 0

    def warm_up(self) -> float:
        """One fast step on a synthetic peel (the first ``torch.func`` call of a process costs
        seconds); returns its wall time, s. The stepper's state is left as it was."""
        from .synthetic import synthetic_trajectory

        t0 = time.perf_counter()
        win = trajectory_windows(synthetic_trajectory(0, max(self.h + 2, 12)), self.h)
        self.adapt(win.to_torch())
        return time.perf_counter() - t0

    def start(self, task: int) -> None:
        """A new task: the model in use is the prior again."""
        self.task, self.model, self.steps, self.results, self._last_n = task, self.prior, 0, [], 0

    def due(self, n: int, last_n: int | None = None) -> bool:
        """Whether a fast step is due with ``n`` samples of the task recorded and the last one
        taken at ``last_n`` samples (default: this stepper's last step in the task)."""
        c, last = self.cfg, self._last_n if last_n is None else last_n
        return (c.enabled and not getattr(self.prior, "needs_time", False)
                and n - c.fast_holdout >= c.fast_min_samples and n - last >= c.fast_every)

    def observe(self, history: Trajectory) -> FastResult | None:
        """The fast step on ``history`` (the running task so far) when one is due, else None."""
        n = len(history)
        if not self.due(n):
            return None
        self._last_n = n
        result, model = self.step(history)
        self.results.append(result)
        if result.accepted:
            self.model = model
        return result

    def step(self, history: Trajectory) -> tuple[FastResult, torch.nn.Module]:
        """Fit on the samples before the cut, check on the held-out ones (module doc 1-4)."""
        t0 = time.perf_counter()
        n = len(history)
        cut = n - self.cfg.fast_holdout
        win = trajectory_windows(history, self.h)
        target = np.arange(len(win)) + 1
        fit, check = win.subset(np.flatnonzero(target < cut)), win.subset(
            np.flatnonzero(target >= cut))
        fast = self.adapt(fit.to_torch())
        e_prior = one_step_error(self.prior, check)
        e_use = e_prior if self.model is self.prior else one_step_error(self.model, check)
        e_fast = one_step_error(fast, check)
        accepted = bool(np.isfinite(e_fast) and e_fast < (1.0 - self.cfg.fast_margin) * e_use)
        self.steps += 1
        return FastResult(self.task, self.steps, n, cut, e_prior, e_use, e_fast, accepted,
                          time.perf_counter() - t0), fast

    def fast_parameters(self) -> dict[str, Tensor]:
        """The parameters the fast step moves (detached): all trainable ones, or the output
        layer's (the last two: weight and bias) with ``fast_params: head``."""
        named = [(k, p.detach()) for k, p in self.prior.named_parameters() if p.requires_grad]
        return dict(named[-2:] if self.cfg.fast_params == "head" else named)

    def adapt(self, fit: Windows) -> torch.nn.Module:
        """Eq. 26, ``fast_steps`` times from the prior on ``fit``: a new model, prior unchanged."""
        was_training = self.prior.training
        self.prior.eval()
        try:
            params = self.fast_parameters()

            def loss(p: dict[str, Tensor]) -> Tensor:
                pred = functional_call(self.prior, p, (fit.hist, fit.v_next), strict=False)
                return self.loss_fn(pred, fit)

            for _ in range(self.cfg.fast_steps):
                g = grad(loss)(params)
                norm = float(torch.sqrt(sum((v.detach() ** 2).sum() for v in g.values())))
                clip = self.cfg.fast_grad_clip
                step = self.cfg.fast_alpha * (clip / norm if 0 < clip < norm else 1.0)
                params = {k: params[k] - step * g[k] for k in params}
        finally:
            self.prior.train(was_training)
        fast = copy.deepcopy(self.prior)
        with torch.no_grad():
            named = dict(fast.named_parameters())
            for k, v in params.items():
                named[k].copy_(v)
        fast.eval()
        return fast
