"""The model's predictions on recorded samples, and the response to a candidate term.

* :func:`one_step`: F_{k+1} from the measured history (Eq. 1), every sample;
* :func:`open_loop`: S model steps fed the model's *own* predicted forces and the *measured*
  speeds (and q), as MPPI uses the model (Algorithm 2 line 9) -- the residual that shows an
  effect which the one-step prediction partly sees in its force history;
* :func:`term_responses`: how one model step changes when a candidate term g = c phi is added
  as compensation, F = f(x - g, v) + g (:mod:`peel_model.compensated`), per unit c:
  d F_{k+1} / d c = e_ch phi(x_{k+1}) - sum_j dF_{k+1}/dF_j phi(x_j), with the model's gradient
  with respect to its force history from autograd (exact linearisation at c = 0);
* :func:`speed_one_step` / :func:`speed_open_loop`: the robot's speed from the commands, Eq. 2's
  mean v = u, or with the velocity terms of a compensated model.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from peel_model.effect_terms import FORCE_CHANNELS, Candidate, Rows

from .data import Horizons, Steps

_CHUNK = 4096


def _dtype(model: Any) -> torch.dtype:
    return next(model.parameters()).dtype


def _kwargs(model: Any, t_next: torch.Tensor) -> dict:
    return {"t_next": t_next} if getattr(model, "needs_time", False) else {}


@torch.no_grad()
def one_step(model: Any, s: Steps) -> np.ndarray:
    """Predicted F_{k+1} ``[n, 2]`` for every sample."""
    dt = _dtype(model)
    out = []
    for a in range(0, len(s), _CHUNK):
        b = slice(a, a + _CHUNK)
        hist = torch.as_tensor(s.hist[b], dtype=dt)
        out.append(model.predict(hist, torch.as_tensor(s.v_next[b], dtype=dt),
                                 **_kwargs(model, torch.as_tensor(s.t_next[b], dtype=dt))))
    return torch.cat(out).double().numpy() if out else np.zeros((0, 2))


def _halves(model: Any) -> tuple[Any, Any, Any]:
    """(f_theta, the step before it, the step after it) of a plain or a compensated model
    (:meth:`~peel_model.compensated.CompensatedPredictor.base_input` / ``output``)."""
    if hasattr(model, "base_input"):
        return model.base, model.base_input, model.output
    return model, lambda hist, v, t=None: (hist, v, None), lambda f, a: f


def _shared_base(parts: Sequence[tuple[Any, Any, Any]]) -> Any:
    base = parts[0][0]
    if any(p[0] is not base for p in parts):
        raise ValueError("models rolled out together must share one f_theta")
    return base


def rollout_many(models: Sequence[Any], rows: Sequence[torch.Tensor], steps: int,
                 t: Sequence[torch.Tensor | None] | None = None) -> list[torch.Tensor]:
    """:func:`rollout` of each model on its own rows, for models that share one f_theta (the
    plain model and corrected copies of it): per step, each model's terms are removed from its
    rows' force history, f_theta runs *once* on all rows, and each model's terms are added
    back. At a few hundred rows f_theta's cost is mostly per call, not per row, so the
    selection's fold scores and the held-out decision's alternatives run together."""
    parts = [_halves(m) for m in models]
    base = _shared_base(parts)
    h, ts = int(base.h), list(t) if t is not None else [None] * len(models)
    hists = [r[:, :h] for r in rows]
    sizes = [len(r) for r in rows]
    outs: list[list[torch.Tensor]] = [[] for _ in models]
    for s in range(steps):
        ins = [before(hist, r[:, h + s, 1], tt[:, h + s] if tt is not None else None)
               for (_, before, _), hist, r, tt in zip(parts, hists, rows, ts, strict=True)]
        f = base.predict(torch.cat([x[0] for x in ins]), torch.cat([x[1] for x in ins]))
        for i, (fi, x) in enumerate(zip(f.split(sizes), ins, strict=True)):
            fo = parts[i][2](fi, x[2])
            outs[i].append(fo)
            row = torch.cat([rows[i][:, h + s, :2], fo], dim=1)
            hists[i] = torch.cat([hists[i][:, 1:], row[:, None]], dim=1)
    return [torch.stack(o, dim=1) for o in outs]


def rollout(model: Any, rows: torch.Tensor, steps: int,
            t: torch.Tensor | None = None) -> torch.Tensor:
    """F_hat ``[n, steps, 2]`` from ``rows [n, h + steps, 4]`` (q, v, fx, fz): step s is fed the
    measured (q, v) of row h + s and the forces predicted before it (Algorithm 2 line 9);
    ``t [n, h + steps]``, the sample times, for a model with time terms. Differentiable in the
    model's parameters (:mod:`.adapt` trains through it)."""
    return rollout_many([model], [rows], steps, [t])[0]


def _pieces(n: Sequence[int]) -> list[list[tuple[int, slice]]]:
    """(model, row slice) pieces of at most :data:`_CHUNK` rows, packed into batches of at most
    :data:`_CHUNK` rows in order."""
    batches: list[list[tuple[int, slice]]] = [[]]
    room = _CHUNK
    for i, rows in enumerate(n):
        for a in range(0, rows, _CHUNK):
            size = min(_CHUNK, rows - a)
            if size > room:
                batches.append([])
                room = _CHUNK
            batches[-1].append((i, slice(a, a + size)))
            room -= size
    return [b for b in batches if b]


@torch.no_grad()
def open_loop_many(models: Sequence[Any], hzs: Sequence[Horizons]) -> list[np.ndarray]:
    """:func:`open_loop` of each model on its horizons, batched by :func:`rollout_many`."""
    if not models:
        return []
    _shared_base([_halves(m) for m in models])
    dt = _dtype(models[0])
    steps = {hz.steps for hz in hzs}
    if len(steps) != 1:
        raise ValueError(f"open_loop_many: horizons of different lengths {sorted(steps)}")
    out: list[list[np.ndarray]] = [[] for _ in models]
    for batch in _pieces([len(hz) for hz in hzs]):
        pred = rollout_many([models[i] for i, _ in batch],
                            [torch.as_tensor(hzs[i].rows[b], dtype=dt) for i, b in batch],
                            hzs[0].steps,
                            [torch.as_tensor(hzs[i].t[b], dtype=dt) for i, b in batch])
        for (i, _), p in zip(batch, pred, strict=True):
            out[i].append(p.double().numpy())
    return [np.concatenate(o) if o else np.zeros((0, hzs[0].steps, 2)) for o in out]


def open_loop(model: Any, hz: Horizons) -> np.ndarray:
    """Predicted forces ``[n, S, 2]`` over each horizon (:func:`rollout`), in chunks."""
    return open_loop_many([model], [hz])[0]


def history_gradient(model: Any, s: Steps) -> np.ndarray:
    """dF_{k+1} / dF_j: ``[n, 2 (output), h (row j), 2 (input channel)]``."""
    dt = _dtype(model)
    out = []
    for a in range(0, len(s), _CHUNK):
        b = slice(a, a + _CHUNK)
        hist = torch.as_tensor(s.hist[b], dtype=dt).clone().requires_grad_(True)
        pred = model.predict(hist, torch.as_tensor(s.v_next[b], dtype=dt),
                             **_kwargs(model, torch.as_tensor(s.t_next[b], dtype=dt)))
        grads = []
        for o in range(2):
            (g,) = torch.autograd.grad(pred[:, o].sum(), hist, retain_graph=o == 0)
            grads.append(g[:, :, 2:4])
        out.append(torch.stack(grads, dim=1).detach().double())
    return torch.cat(out).numpy()


def term_responses(s: Steps, pred: np.ndarray, grad: np.ndarray,
                   candidates: Sequence[Candidate], dt_s: float
                   ) -> dict[tuple[str, str], tuple[Candidate, np.ndarray]]:
    """``{(candidate key, channel): (candidate, J [n, 2 (output), n_basis])}`` for the force
    candidates: the change of the one-step prediction per unit coefficient (module docstring)."""
    h = s.hist.shape[1]
    q = np.concatenate([s.hist[:, :, 0], (s.hist[:, -1, 0] + s.v_next * dt_s)[:, None]], 1)
    v = np.concatenate([s.hist[:, :, 1], s.v_next[:, None]], 1)
    t = s.t_next[:, None] - dt_s * np.arange(h, -1, -1)[None, :]
    f = np.concatenate([s.hist[:, :, 2:4], pred[:, None, :]], 1)
    rows = Rows(q=torch.as_tensor(q), v=torch.as_tensor(v), t=torch.as_tensor(t),
                f=torch.as_tensor(f))
    out: dict[tuple[str, str], tuple[Candidate, np.ndarray]] = {}
    for cand in candidates:
        for ch_name in FORCE_CHANNELS:
            if ch_name not in cand.spec.channels:
                continue
            ch = FORCE_CHANNELS.index(ch_name)
            phi = cand.basis(rows, ch).numpy()  # [n, h+1, nb]
            resp = -np.einsum("noj,njb->nob", grad[:, :, :, ch], phi[:, :h])
            resp[:, ch, :] += phi[:, h]
            out[(cand.key, ch_name)] = (cand, resp)
    return out


def speed_one_step(model: Any | None, v_k: np.ndarray, u_k: np.ndarray) -> np.ndarray:
    """v_{k+1} predicted from u_k (and v_k): Eq. 2's mean u_k, or the model's speed response."""
    if model is None or not getattr(model, "velocity_terms", None):
        return u_k.copy()
    with torch.no_grad():
        return model.speed(torch.as_tensor(u_k), torch.as_tensor(v_k)).numpy()


def speed_open_loop(model: Any | None, hz: Horizons) -> np.ndarray:
    """Speeds ``[n, S]`` over each horizon from the commands alone (from the measured v_k)."""
    h = hz.rows.shape[1] - hz.steps
    prev = hz.rows[:, h - 1, 1].copy()
    out = np.empty(hz.u.shape)
    for k in range(hz.steps):
        prev = speed_one_step(model, prev, hz.u[:, k])
        out[:, k] = prev
    return out
