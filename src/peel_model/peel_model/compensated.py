"""The forward model with a compensation term: F = f_theta(x with the effect removed, v) + g.

The paper's conclusion: the model "can be corrected online by adding a compensation term".
``peel residual`` (docs/residual.md) finds physical effects the model lacks and adds them here as
named terms g = sum_k c_k phi_k(q, v, t, F) (:mod:`~peel_model.effect_terms`):

* **one model step** (Eq. 1): the terms' contribution is removed from the measured force history
  (so f_theta sees forces of the kind it was trained on), f_theta predicts the effect-free force,
  and the terms at the next sample are added back. With cross-talk terms the measured forces are
  m = (I + C) F + A (C the 2x2 cross-talk matrix, A the additive terms), so "removed" means
  F = (I + C)^-1 (m - A) and the output is (I + C) F_next + A_next;
* **speed response**: velocity terms correct Eq. 2's mean v_{k+1} = u_k to
  v_{k+1} = u_k + sum c phi(u_k, v_k) (actuator lag, scale, offset). They act only where the
  model is fed *commands*: in the planner's rollouts, where the planner's reference dynamics
  (``peel_planner_node.dynamics.ReferenceDynamics``) applies :meth:`speed` and passes the
  sample times to :meth:`predict` (the fused rollout reproduces only the plain network, so the
  planner's capability check gives such a model the reference dynamics).

The coefficients are plain numbers, not parameters: MAML (Algorithm 1) and baseline 2 adapt
f_theta's parameters through ``functional_call`` / ``parameters()`` with the terms held. Time
terms need the sample times: :meth:`predict` takes ``t_next`` (time of sample k+1 in the task,
s); without it they contribute nothing. The module is ``ForcePredictor``-compatible (``h``,
``predict``, ``forward``, ``out_std``, ``psi_from_force``, ...) and is saved by
:func:`~peel_model.checkpoint.save_checkpoint` as f_theta's safetensors plus the terms
in the JSON.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from peel_msgs_py.errors import PeelError

from .effect_terms import FORCE_CHANNELS, VELOCITY_CHANNEL, Rows, Term
from .predictor import ForcePredictor, Normalization

FORM = ("F = f_theta(x with the terms removed, v) + sum_k c_k phi_k(q, v, t, F); "
        "v_{k+1} = u_k + sum_k c_k phi_k(u_k, v_k)")


class CompensatedPredictor(nn.Module):
    """f_theta (a :class:`ForcePredictor`) plus fixed physical terms (module docstring)."""

    def __init__(self, base: ForcePredictor, terms: Sequence[Term], *, dt_s: float = 0.1) -> None:
        super().__init__()
        if isinstance(base, CompensatedPredictor):
            terms = [*base.terms, *terms]
            base = base.base
        self.base = base
        self.dt_s = float(dt_s)
        self.terms: tuple[Term, ...] = tuple(terms)
        seen = set()
        for term in self.terms:
            key = (term.candidate.key, term.channel)
            if key in seen:
                raise PeelError(f"compensation term {term.candidate.key} on {term.channel} is "
                                "given twice")
            seen.add(key)
        self.force_terms = [t for t in self.terms if t.channel in FORCE_CHANNELS]
        self.velocity_terms = [t for t in self.terms if t.channel == VELOCITY_CHANNEL]
        self.cross = np.zeros((2, 2))
        for t in self.force_terms:
            if t.candidate.spec.uses_force:
                ch = FORCE_CHANNELS.index(t.channel)
                self.cross[ch, 1 - ch] += t.coef[0]
        if abs(1.0 - self.cross[0, 1] * self.cross[1, 0]) < 1e-3:
            raise PeelError("the cross-talk coefficients make the channels inseparable "
                            "(1 - c_xz c_zx = 0)")
        self._coef_cache: dict[tuple, list[Tensor]] = {}
        for t in self.velocity_terms:
            if t.candidate.family == "actuator_lag" and not 0.0 <= t.coef[0] < 1.0:
                raise PeelError(f"actuator lag coefficient {t.coef[0]:g} is outside [0, 1): not "
                                "a stable first-order lag")

    # -- ForcePredictor compatibility ---------------------------------------------------------
    @property
    def h(self) -> int:
        return self.base.h

    @property
    def arch(self) -> str:
        return self.base.arch

    @property
    def cfg(self) -> Any:
        return self.base.cfg

    @property
    def normalization(self) -> Normalization:
        return self.base.normalization

    @property
    def out_std(self) -> Tensor:
        return self.base.out_std

    @property
    def pad_compliance(self) -> Tensor:
        return self.base.pad_compliance

    @property
    def needs_time(self) -> bool:
        """True when a term depends on the time in the task (:meth:`predict`'s ``t_next``)."""
        return any(t.candidate.spec.uses_time for t in self.force_terms)

    def psi_from_force(self, fz: Tensor) -> Tensor:
        return self.base.psi_from_force(fz)

    # -- the terms ----------------------------------------------------------------------------
    def _coefs(self, terms: Sequence[Term], like: Tensor) -> list[Tensor]:
        key = (id(terms), like.dtype, like.device)
        hit = self._coef_cache.get(key)
        if hit is None:
            # normal tensors even when first asked for under inference mode (the planner's
            # rollouts): the same model may be adapted with autograd (MAML) afterwards
            with torch.inference_mode(False):
                hit = [torch.tensor(t.coef, dtype=like.dtype, device=like.device) for t in terms]
            self._coef_cache[key] = hit
        return hit

    def additive(self, rows: Rows) -> Tensor:
        """A: the terms that do not depend on the forces, ``[..., L, 2]`` (N)."""
        out = torch.zeros((*rows.q.shape, 2), dtype=rows.q.dtype, device=rows.q.device)
        for t, coef in zip(self.force_terms, self._coefs(self.force_terms, rows.q), strict=True):
            spec = t.candidate.spec
            if spec.uses_force or (spec.uses_time and rows.t is None):
                continue
            ch = FORCE_CHANNELS.index(t.channel)
            out[..., ch] += t.candidate.basis(rows, ch) @ coef
        return out

    def _mix(self, f: Tensor, inverse: bool) -> Tensor:
        """(I + C) f, or (I + C)^-1 f, on the last axis (forces)."""
        if not self.cross.any():
            return f
        m = np.eye(2) + self.cross
        if inverse:
            m = np.linalg.inv(m)
        return f @ torch.as_tensor(m.T, dtype=f.dtype, device=f.device)

    def rows(self, hist: Tensor, v_next: Tensor, t_next: Tensor | None) -> Rows:
        """The h history rows plus the next sample (q_next = q_k + v_next dt) as :class:`Rows`."""
        q = torch.cat([hist[..., 0], (hist[:, -1, 0] + v_next * self.dt_s)[:, None]], dim=1)
        v = torch.cat([hist[..., 1], v_next[:, None]], dim=1)
        t = None
        if t_next is not None:
            steps = torch.arange(self.h, -1, -1, dtype=hist.dtype, device=hist.device)
            t = t_next.to(hist.dtype)[:, None] - steps * self.dt_s
        return Rows(q=q, v=v, t=t)

    def predict(self, hist: Tensor, v_next: Tensor, t_next: Tensor | None = None) -> Tensor:
        """F_{k+1} ``[B, 2]`` from ``hist [B, h, 4]``, ``v_next [B]`` and optionally the time of
        sample k+1 ``t_next [B]`` (s in the task)."""
        if hist.dim() != 3 or hist.shape[1] != self.h or hist.shape[2] != 4:
            raise ValueError(f"hist must have shape [B, {self.h}, 4], got {list(hist.shape)}")
        base_hist, v_next, a = self.base_input(hist, v_next, t_next)
        return self.output(self.base.predict(base_hist, v_next), a)

    def base_input(self, hist: Tensor, v_next: Tensor, t_next: Tensor | None = None
                   ) -> tuple[Tensor, Tensor, Tensor | None]:
        """The first half of :meth:`predict`: (f_theta's history, with the terms removed from
        its forces, v_next, the additive terms A ``[B, h + 1, 2]`` or None without force
        terms). Batched rollouts of several corrected models on one f_theta call it per model
        and f_theta once on all rows (``peel_residual.predict.rollout_many``)."""
        dtype = self.base.in_mean.dtype
        hist, v_next = hist.to(dtype), v_next.to(dtype)
        if not self.force_terms:
            return hist, v_next, None
        a = self.additive(self.rows(hist, v_next, t_next))
        clean = self._mix(hist[..., 2:4] - a[:, : self.h], inverse=True)
        return torch.cat([hist[..., :2], clean], dim=-1), v_next, a

    def output(self, f: Tensor, a: Tensor | None) -> Tensor:
        """The second half of :meth:`predict`: (I + C) F_next + A_next from f_theta's ``f``."""
        if a is None:
            return f
        return self._mix(f, inverse=False) + a[:, self.h]

    def forward(self, hist: Tensor, v_next: Tensor, t_next: Tensor | None = None) -> Tensor:
        return self.predict(hist, v_next, t_next)

    @torch.no_grad()
    def predict_np(self, hist: np.ndarray, v_next: np.ndarray,
                   t_next: np.ndarray | None = None) -> np.ndarray:
        """NumPy convenience: ``[B, h, 4]``, ``[B]`` (, ``[B]``) -> ``[B, 2]`` float64."""
        dev = self.base.in_mean.device

        def tt(a: np.ndarray) -> Tensor:
            return torch.as_tensor(a, dtype=torch.float32, device=dev)

        out = self.predict(tt(hist), tt(v_next), None if t_next is None else tt(t_next))
        return out.cpu().numpy().astype(np.float64)

    def speed(self, u: Tensor, v_prev: Tensor) -> Tensor:
        """v_{k+1} for the command u_k and the previous speed v_k (Eq. 2's mean + the terms)."""
        out = u.clone()
        rows = Rows(q=torch.zeros_like(u), v=v_prev, u=u)
        for t, coef in zip(self.velocity_terms, self._coefs(self.velocity_terms, u), strict=True):
            out = out + t.candidate.basis(rows) @ coef
        return out

    # -- persistence --------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The ``compensation`` block of the checkpoint JSON."""
        return {"form": FORM, "dt_s": self.dt_s, "terms": [t.to_json() for t in self.terms]}

    @classmethod
    def from_json(cls, base: ForcePredictor, obj: Any) -> CompensatedPredictor:
        """Rebuild from :meth:`to_json`; raises PeelError naming what is wrong."""
        if not isinstance(obj, dict) or not isinstance(obj.get("terms"), list):
            raise PeelError("compensation must be an object with a list 'terms'")
        dt = obj.get("dt_s")
        if not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
            raise PeelError(f"compensation dt_s must be a positive number, got {dt!r}")
        return cls(base, [Term.from_json(t) for t in obj["terms"]], dt_s=float(dt))


def corrected_model(model: Any, terms: Sequence[Term], dt_s: float) -> CompensatedPredictor:
    """``model`` with ``terms`` added; a term the model already has gets the coefficients added."""
    base, old = (model.base, list(model.terms)) if isinstance(model, CompensatedPredictor) \
        else (model, [])
    merged = {(t.candidate.key, t.channel): t for t in old}
    for t in terms:
        prev = merged.get((t.candidate.key, t.channel))
        if prev is not None:
            t = Term(t.candidate, t.channel, tuple(a + b for a, b in zip(prev.coef, t.coef,
                                                                          strict=True)), t.coef_std)
        merged[(t.candidate.key, t.channel)] = t
    return CompensatedPredictor(base, list(merged.values()), dt_s=dt_s)
