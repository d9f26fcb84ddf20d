"""The ``ol-mppi-fast`` arm of ``peel experiment``: Algorithm 1 between peels plus the fast step
inside each peel (:mod:`model_learner_node.fast_step`).

In the node graph the learner takes the fast step beside the planner and swaps the fast model in
over the planner's parameter service; here, in one process, :class:`FastPolicy` takes it just
before the plan of the control period in which it falls due (the same samples, the same check),
times it apart from the plan, and sets the planner's dynamics to the accepted fast model
(:meth:`peel_planner_node.mppi.Planner.set_dynamics`). The prior theta is the arm's predictor,
which only the between-peel update changes.

:func:`task_record` is the arm's per-task record (``results.json`` ``fast``): the fast steps
(identity, errors, time) and the one-step force error (Eq. 39, both channels) of the model in
use at each sample against the pretrained model's on the same samples, per sample and over the
task's second half.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from model_learner_node.fast_step import FastStepper, load_fast_config
from model_learner_node.metrics import predict_windows
from peel_model.windows import trajectory_windows
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.dynamics import learned_dynamics

FAST = "ol-mppi-fast"


def fast_stepper(method: str, predictor: Any, learner_overrides: str | None,
                 changes: dict[str, Any] | None = None) -> FastStepper | None:
    """The arm's stepper on ``predictor`` (fast step on even when the YAML has it off: the
    shipped ``online.fast_every`` 0 means 5 here, one control period), None for other arms."""
    if method != FAST:
        return None
    cfg = load_fast_config(learner_overrides, **(changes or {}))
    if not cfg.enabled:
        cfg = load_fast_config(learner_overrides, **{**(changes or {}), "fast_every": 5})
    stepper = FastStepper(predictor, cfg)
    stepper.warm_up()  # as the learner node does at start: fast_s is the step alone
    return stepper


@dataclass
class FastPolicy:
    """``policy(history)`` of one task: the fast step when due, then the plan (module doc)."""

    planner: Any
    stepper: FastStepper
    dynamics_cfg: Any
    plan_times: list[float]
    swaps: list[tuple[int, Any]] = field(default_factory=list)  # (samples at swap, model)

    def __call__(self, history: Trajectory) -> float:
        result = self.stepper.observe(history)
        if result is not None and result.accepted:
            self.planner.set_dynamics(learned_dynamics(self.stepper.model, self.dynamics_cfg))
            self.swaps.append((len(history), self.stepper.model))
        t0 = time.perf_counter()
        u = self.planner.plan(history)
        self.plan_times.append(time.perf_counter() - t0)
        return u


def _errors(model: Any, win: Any) -> np.ndarray:
    """Per-window one-step force error ||F_{k+1} - f|| (N), both channels."""
    was = model.training
    model.eval()
    try:
        pred = predict_windows(model, win)
    finally:
        model.train(was)
    return np.sqrt(np.sum((win.f_next - pred) ** 2, axis=1))


def in_use_errors(traj: Trajectory, prior: Any, swaps: list[tuple[int, Any]]) -> np.ndarray:
    """The error of the model in use at each target sample j = 1..T-1: the last fast model
    swapped in with at most j samples recorded (it planned sample j), else the prior."""
    win = trajectory_windows(traj, int(prior.h))
    out = _errors(prior, win)
    target = np.arange(len(win)) + 1
    for n_at, model in swaps:
        sel = target >= n_at
        out[sel] = _errors(model, win)[sel]
    return out


def task_record(traj: Trajectory, policy: FastPolicy, pretrained: Any) -> dict[str, Any]:
    """The ``fast`` record of one task (module docstring)."""
    res = policy.stepper.results
    e_use = in_use_errors(traj, policy.stepper.prior, policy.swaps)
    e_pre = _errors(pretrained, trajectory_windows(traj, int(pretrained.h)))
    half = len(e_use) // 2
    rms = lambda e: float(np.sqrt(np.mean(e[half:] ** 2))) if len(e) > half else None  # noqa: E731
    return {
        "steps": len(res), "accepted": sum(r.accepted for r in res),
        "fast_s": [r.fast_s for r in res],
        "identities": [r.identity() for r in res if r.accepted],
        "results": [r.as_dict() for r in res],
        "error_in_use_second_half_n": rms(e_use),
        "error_pretrained_second_half_n": rms(e_pre),
        "error_in_use_n": [float(x) for x in e_use],
        "error_pretrained_n": [float(x) for x in e_pre],
    }
