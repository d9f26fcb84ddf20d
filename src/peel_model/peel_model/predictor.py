"""ForcePredictor: the forward model f_theta(x_t, v_t) in the paper's units (Eq. 1-2, 3.1).

``predict(hist [B, h, 4], v_next [B]) -> [B, 2]``: from the last h samples ``[q_mm, v_mmps, fx_N,
fz_N]`` (rows k-h+1..k) and the velocity v_{k+1} (mm/s) applied over the next sample, the contact
forces ``(fx_N, fz_N)`` at sample k+1. ``forward`` is ``predict`` so that
``torch.func.functional_call(predictor, params, (hist, v_next))`` works (MAML, Eq. 26-27).

Decisions:

* **Increment head.** The body predicts the normalised increment dF = F_{k+1} - F_k and the
  predictor returns F_k + dF. At 100 ms sampling F_{k+1} is close to F_k; learning the change
  instead of the level removes the large persistent part from the regression target, so a small
  network trains in minutes and multi-step planner rollouts start from the measured force.
* **Normalisation inside.** Per-column mean/std of the inputs and of dF, fitted on the training
  split only (:func:`fit_normalization`), are buffers of this module: they are saved in the
  checkpoint, move with ``.to(device)`` and are not trained (``functional_call`` over
  ``named_parameters()`` leaves them alone).
* **Penetration psi for L_PENE (Eq. 24).** The model does not get a third output: psi is the
  indentation of the blade into the pad, which in the contact model is the pad's elastic
  compression under the vertical reaction, psi ~ c * F_RZ. The compliance ``c`` (mm/N) is a buffer
  fitted on the training split by least squares through the origin on the recorded ``psi``
  (:func:`fit_normalization`); :meth:`psi_from_force` maps predicted F_RZ to predicted psi, so
  L_PENE penalises *force predictions* that imply an unphysical indentation -- the paper's purpose
  ("avoid ... results which imply the wedge blade penetrating into the adsorption pad too deep").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from .config import ModelConfig
from .model import N_INPUTS, N_OUTPUTS, build_body

INPUT_COLUMNS: tuple[str, ...] = ("q_mm", "v_mmps", "fx_N", "fz_N")
OUTPUT_COLUMNS: tuple[str, ...] = ("fx_N", "fz_N")


@dataclass(frozen=True)
class Normalization:
    """Statistics of the training split (3.3): inputs, force increments, pad compliance."""

    in_mean: tuple[float, ...] = (0.0,) * N_INPUTS
    in_std: tuple[float, ...] = (1.0,) * N_INPUTS
    out_mean: tuple[float, ...] = (0.0,) * N_OUTPUTS
    out_std: tuple[float, ...] = (1.0,) * N_OUTPUTS
    pad_compliance_mm_per_n: float = 0.02

    def to_json(self) -> dict:
        return {
            "in_columns": list(INPUT_COLUMNS),
            "in_mean": list(self.in_mean),
            "in_std": list(self.in_std),
            "out_columns": ["d" + c for c in OUTPUT_COLUMNS],
            "out_mean": list(self.out_mean),
            "out_std": list(self.out_std),
            "pad_compliance_mm_per_n": self.pad_compliance_mm_per_n,
        }


def fit_normalization(
    trajectories: Sequence, h: int, *, default_compliance: float = 0.02, min_std: float = 1e-3
) -> Normalization:
    """Normalisation fitted on (training) trajectories only.

    Input stats over every sample; output stats over the one-step increments F_{k+1} - F_k;
    pad compliance c = sum(psi*fz)/sum(fz^2) over samples with finite psi (``default_compliance``
    if none). ``h`` is accepted for symmetry with the windows (the stats do not depend on it).
    """
    del h
    if not trajectories:
        raise ValueError("cannot fit normalisation on an empty training split")
    states = np.concatenate([t.states() for t in trajectories], axis=0)
    deltas = np.concatenate(
        [np.diff(np.stack([t.fx, t.fz], axis=1), axis=0) for t in trajectories if len(t) > 1],
        axis=0,
    )
    fz = np.concatenate([t.fz for t in trajectories])
    psi = np.concatenate([t.psi for t in trajectories])
    ok = np.isfinite(psi) & np.isfinite(fz)
    denom = float(np.sum(fz[ok] ** 2))
    comp = float(np.sum(psi[ok] * fz[ok]) / denom) if ok.any() and denom > 0 else default_compliance
    return Normalization(
        in_mean=tuple(float(x) for x in states.mean(0)),
        in_std=tuple(float(max(x, min_std)) for x in states.std(0)),
        out_mean=tuple(float(x) for x in deltas.mean(0)),
        out_std=tuple(float(max(x, min_std)) for x in deltas.std(0)),
        pad_compliance_mm_per_n=comp,
    )


class ForcePredictor(nn.Module):
    """Normalisation + network body; inputs and outputs in the paper's units (see module doc)."""

    def __init__(self, cfg: ModelConfig, norm: Normalization | None = None):
        super().__init__()
        cfg.check()
        self.cfg = cfg
        self.arch = cfg.arch
        self.h = cfg.h
        self.body = build_body(cfg)
        norm = norm or Normalization()
        self.register_buffer("in_mean", torch.tensor(norm.in_mean, dtype=torch.float32))
        self.register_buffer("in_std", torch.tensor(norm.in_std, dtype=torch.float32))
        self.register_buffer("out_mean", torch.tensor(norm.out_mean, dtype=torch.float32))
        self.register_buffer("out_std", torch.tensor(norm.out_std, dtype=torch.float32))
        self.register_buffer(
            "pad_compliance", torch.tensor([norm.pad_compliance_mm_per_n], dtype=torch.float32)
        )

    @property
    def normalization(self) -> Normalization:
        def tup(t: Tensor) -> tuple[float, ...]:
            return tuple(float(x) for x in t.detach().cpu().tolist())

        return Normalization(
            tup(self.in_mean), tup(self.in_std), tup(self.out_mean), tup(self.out_std),
            float(self.pad_compliance.item()),
        )

    def set_normalization(self, norm: Normalization) -> None:
        """Overwrite the normalisation buffers (before training)."""
        with torch.no_grad():
            for name in ("in_mean", "in_std", "out_mean", "out_std"):
                getattr(self, name).copy_(torch.tensor(getattr(norm, name)))
            self.pad_compliance.fill_(norm.pad_compliance_mm_per_n)

    def normalized_increment(self, hist: Tensor, v_next: Tensor) -> Tensor:
        """The body's output: normalised dF, ``[B, 2]``."""
        x = (hist - self.in_mean) / self.in_std
        vn = (v_next - self.in_mean[1]) / self.in_std[1]
        return self.body(x, vn)

    def predict(self, hist: Tensor, v_next: Tensor) -> Tensor:
        """F_{k+1} = F_k + dF, ``[B, 2]`` (fx_N, fz_N) (Eq. 1)."""
        if hist.dim() != 3 or hist.shape[1] != self.h or hist.shape[2] != N_INPUTS:
            raise ValueError(
                f"hist must have shape [B, {self.h}, {N_INPUTS}], got {list(hist.shape)}"
            )
        if v_next.shape != hist.shape[:1]:
            raise ValueError(f"v_next must have shape [{hist.shape[0]}], got {list(v_next.shape)}")
        hist = hist.to(self.in_mean.dtype)
        v_next = v_next.to(self.in_mean.dtype)
        d = self.normalized_increment(hist, v_next)
        return hist[:, -1, 2:4] + self.out_mean + self.out_std * d

    def forward(self, hist: Tensor, v_next: Tensor) -> Tensor:
        return self.predict(hist, v_next)

    def psi_from_force(self, fz: Tensor) -> Tensor:
        """Predicted blade indentation psi (mm) from F_RZ (N): psi = c * F_RZ (Eq. 24)."""
        return self.pad_compliance * fz

    def attention_weights(self, hist: Tensor) -> Tensor:
        """Attention weights ``[B, h-1, n_scales]`` (Eq. 9); only for ``ours`` / ``cnn-lstm``."""
        if self.arch == "mlp":
            raise ValueError("the mlp baseline has no attention module")
        x = (hist.to(self.in_mean.dtype) - self.in_mean) / self.in_std
        _, w, _ = self.body.features(x)
        return w

    @torch.no_grad()
    def predict_np(self, hist: np.ndarray, v_next: np.ndarray) -> np.ndarray:
        """NumPy convenience: ``[B, h, 4]``, ``[B]`` -> ``[B, 2]`` float64."""
        dev = self.in_mean.device
        out = self.predict(torch.as_tensor(hist, dtype=torch.float32, device=dev),
                           torch.as_tensor(v_next, dtype=torch.float32, device=dev))
        return out.cpu().numpy().astype(np.float64)
