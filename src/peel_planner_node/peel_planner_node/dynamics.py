"""What the planner rolls out: the Dynamics interface, its implementations, and the choice.

A :class:`Dynamics` maps the measured history (a :class:`~peel_msgs_py.trajectory.Trajectory`
ending at the current sample) and N velocity sequences ``v`` [N, S] -- one velocity per 100 ms
model step -- to the predicted samples [N, S, 3] with columns (q_mm, fx_N, fz_N). This is line 9
of Algorithm 2, ``x <- x + F_theta(x, v_t) dt``, batched over the N samples. It is the
planner's one extension point for the motion model (as nav2's motion-model plugin):

- :class:`ReferenceDynamics`: the forward model stepped one model step at a time with
  ``predictor.predict`` (Eq. 1-2). Readable; the definition every faster implementation is
  tested against; runs any model with ``.h`` and ``.predict(hist, v_next)``.
- :class:`~.fused_dynamics.FusedDynamics`: the same function for the ``ours`` / ``cnn-lstm``
  networks, fused (``fused.py``), in fixed sample chunks on worker threads, with an optional
  C++ model-step loop; its settings are ``dynamics.fused.*``.
- :class:`OracleDynamics`: the simulator's exact, noise-free dynamics (the oracle baseline).

:func:`learned_dynamics` chooses between the first two by one capability check
(:func:`~.fused_weights.fused_support`): a model the fused rollout does not reproduce exactly
(the ``mlp`` baseline, a subclass or wrapper of the predictor, such as a model with a
compensation term) gets the reference dynamics.
"""

from __future__ import annotations

import logging
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import DynamicsConfig
from .fused_dynamics import FusedDynamics
from .fused_weights import fused_support
from .history import history_window

_LOG = logging.getLogger(__name__)


@runtime_checkable
class Dynamics(Protocol):
    """Batched forward simulation used by the planner (Algorithm 2, line 9).

    ``rollout`` starts from the end of the history it is given, so the guard's Eq. M7 can
    replay a past sample by passing a shorter history; an implementation that rolls out from
    a state of its own instead sets ``replays_history = False`` (:class:`OracleDynamics`)."""

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        """Predicted (q_mm, fx_N, fz_N) [N, S, 3] for velocities ``v`` [N, S] (mm/s)."""
        ...


class ReferenceDynamics:
    """The forward model F_theta (Eq. 1-2) stepped sample by sample: the definition.

    Model step k: F_{k+1} = predictor.predict(window_k, v_k), q_{k+1} = q_k + v_k dt,
    v_{k+1} = v_k (the command is assumed tracked inside the rollout; Eq. 2's noise is what
    MPPI samples); the window then drops its oldest row and appends [q, v, F]_{k+1}.

    A model with a compensation term (``CompensatedPredictor``, docs/residual.md) extends Eq.
    1-2 in two ways, each read here once from the model, so its terms are in every rollout:

    * ``needs_time``: its ``predict`` takes ``t_next``, the time of sample k+1 in the task; the
      rollout passes t_now + (k+1) dt, t_now the time of the history's last sample;
    * ``velocity_terms`` with ``speed(u_k, v_k)``: Eq. 2's mean v_{k+1} = u_k corrected by the
      model's speed response (actuator lag, scale, offset); the speeds the model is fed, and q,
      follow the response to the sampled commands instead of the commands themselves.
    """

    def __init__(self, predictor: Any, *, dt_s: float = 0.1) -> None:
        if not callable(getattr(predictor, "predict", None)) or not hasattr(predictor, "h"):
            raise PeelError("model must be a ForcePredictor with .h and .predict(hist, v_next)")
        self.predictor, self.h, self.dt_s = predictor, int(predictor.h), float(dt_s)
        try:
            p = next(predictor.parameters())
            self.dtype, self.device = p.dtype, p.device
        except (AttributeError, StopIteration):
            self.dtype, self.device = torch.float32, torch.device("cpu")
        if hasattr(predictor, "eval"):
            predictor.eval()
        model_dt = getattr(predictor, "dt_s", None)
        if model_dt is not None and abs(float(model_dt) - self.dt_s) > 1e-9:
            raise PeelError(f"rollout dt {self.dt_s:g} s differs from the model's "
                            f"{float(model_dt):g} s")
        self.needs_time = bool(getattr(predictor, "needs_time", False))
        speed = getattr(predictor, "speed", None)
        self.speed = speed if callable(speed) and getattr(predictor, "velocity_terms", None) \
            else None

    def speeds(self, u: torch.Tensor, v_now: torch.Tensor) -> torch.Tensor:
        """v_{k+1} [N, S] for the commands ``u`` [N, S] from the current speed ``v_now``: ``u``
        itself (Eq. 2's mean), or the model's speed response applied step by step."""
        if self.speed is None:
            return u
        out = torch.empty_like(u)
        prev = v_now.expand(u.shape[0])
        for k in range(u.shape[1]):
            prev = self.speed(u[:, k], prev)
            out[:, k] = prev
        return out

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        """Predicted (q, fx, fz) [N, S, 3] for ``v`` [N, S] from the end of ``history``."""
        n, s = v.shape
        with torch.inference_mode():
            window = torch.as_tensor(history_window(history, self.h), dtype=self.dtype,
                                     device=self.device).expand(n, self.h, 4)
            v = self.speeds(v.to(dtype=self.dtype, device=self.device), window[0, -1, 1])
            t_now = float(history.t[-1])
            rows = []
            for k in range(s):
                extra = {"t_next": torch.full((n,), t_now + (k + 1) * self.dt_s,
                                              dtype=self.dtype, device=self.device)} \
                    if self.needs_time else {}
                f = self.predictor.predict(window, v[:, k], **extra)  # F_{k+1} (Eq. 1)
                q = window[:, -1, 0] + self.dt_s * v[:, k]  # q_{k+1} = q_k + v_k dt
                row = torch.stack([q, v[:, k], f[:, 0], f[:, 1]], dim=1)
                window = torch.cat([window[:, 1:], row.unsqueeze(1)], dim=1)
                rows.append(row)
            return torch.stack(rows, dim=1)[..., [0, 2, 3]]

    def describe(self) -> str:
        """Which implementation runs, for logs and status."""
        return f"reference dynamics ({type(self.predictor).__name__}.predict per model step)"


def learned_dynamics(predictor: Any, config: DynamicsConfig | None = None) -> Any:
    """The forward model as planner dynamics, per ``dynamics.*``: the fused implementation
    when configured and the model supports it, else the reference (the reason is logged)."""
    config = config if config is not None else DynamicsConfig()
    if config.implementation == "fused":
        reason = fused_support(predictor)
        if reason is None:
            return FusedDynamics(predictor, dt_s=config.dt_s, config=config.fused)
        _LOG.info("peel: reference dynamics for this model (%s)", reason)
    return ReferenceDynamics(predictor, dt_s=config.dt_s)


class OracleDynamics:
    """The simulator's exact, noise-free dynamics (``env.rollout``) as planner dynamics.

    ``env`` is anything with ``rollout(v: ndarray[N, S]) -> ndarray[N, S, 3]`` that simulates
    from its own current state (``PeelEnv``); the history argument is ignored because the env
    already is at the end of it. This package may not import the simulator
    (docs/CONTRACT.md), so the env is duck-typed.
    """

    def __init__(self, env: Any, *, dtype: torch.dtype = torch.float32) -> None:
        if not callable(getattr(env, "rollout", None)):
            raise PeelError("env must provide rollout(v) -> ndarray[N, S, 3]")
        self.env = env
        self.dtype = dtype
        self.replays_history = False  # it rolls out from the env's state, not a past sample

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        """Predicted (q, fx, fz) [N, S, 3] by the env for ``v`` [N, S] (mm/s)."""
        out = np.asarray(self.env.rollout(v.detach().cpu().numpy().astype(np.float64)))
        if out.shape != (*v.shape, 3):
            raise PeelError(f"env.rollout returned shape {out.shape}, expected {(*v.shape, 3)}")
        return torch.as_tensor(out, dtype=self.dtype)

    def describe(self) -> str:
        return f"oracle dynamics ({type(self.env).__name__}.rollout)"
