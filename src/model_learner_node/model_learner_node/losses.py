"""Training loss L_MSE + kappa * L_PENE (paper Eq. 23-25).

* :func:`mse_loss` (Eq. 23): squared force error, each channel divided by the training-split
  standard deviation of its one-step increment before squaring, averaged over the batch. Plain
  Eq. 23 in N^2 would let the larger of F_RX / F_RZ dominate; the scaling balances the channels
  and is exactly the MSE of the network's normalised output.
* :func:`pene_loss` (Eq. 24): mean of min(0, psi_lim - psi)^2 = relu(psi - psi_lim)^2 over the
  batch, with psi the *predicted* indentation (mm): zero while psi <= psi_lim, quadratic beyond.
  Where psi comes from: :meth:`ForcePredictor.psi_from_force` (pad compliance x predicted F_RZ).
* :func:`total_loss` (Eq. 25). Means instead of the paper's sums so kappa does not depend on the
  batch size.
"""

from __future__ import annotations

import torch
from torch import Tensor


def mse_loss(f_hat: Tensor, f_true: Tensor, scale: Tensor | None = None) -> Tensor:
    """Eq. 23, per-channel scaled by ``scale`` (``[2]``), mean over batch and channels."""
    err = f_hat - f_true
    if scale is not None:
        err = err / scale
    return (err**2).mean()


def pene_loss(psi: Tensor, psi_lim: float) -> Tensor:
    """Eq. 24: mean(min(0, psi_lim - psi)^2); zero iff every psi <= psi_lim."""
    return (torch.clamp(psi - psi_lim, min=0.0) ** 2).mean()


def total_loss(
    predictor, hist: Tensor, v_next: Tensor, f_next: Tensor, *, kappa: float, psi_lim: float,
    use_pene: bool = True,
) -> tuple[Tensor, dict[str, float]]:
    """L_MSE + kappa * L_PENE (Eq. 25) for a batch; returns (loss, parts as floats)."""
    f_hat = predictor(hist, v_next)
    l_mse = mse_loss(f_hat, f_next, predictor.out_std)
    if use_pene and kappa > 0:
        l_pene = pene_loss(predictor.psi_from_force(f_hat[:, 1]), psi_lim)
        loss = l_mse + kappa * l_pene
    else:
        l_pene = torch.zeros((), device=f_hat.device)
        loss = l_mse
    return loss, {"mse": float(l_mse.detach()), "pene": float(l_pene.detach())}


_TRAIN_DEFAULTS: dict[str, float] = {}


def _train_default(name: str) -> float:
    if not _TRAIN_DEFAULTS:
        from .config import load_train_config

        cfg = load_train_config()
        _TRAIN_DEFAULTS.update(kappa=cfg.kappa, psi_lim_mm=cfg.psi_lim_mm,
                               pad_compliance_mm_per_n=cfg.pad_compliance_mm_per_n)
    return _TRAIN_DEFAULTS[name]


def batch_loss(
    pred: Tensor, batch, predictor=None, *, kappa: float | None = None,
    psi_lim: float | None = None, use_pene: bool = True,
) -> Tensor:
    """Eq. 25 on predictions ``pred [B, 2]`` of a batch with ``.target [B, 2]`` (paper units).

    For callers that run the network themselves (MAML via ``functional_call``). Pass the
    ``predictor`` so its normalisation (channel scales) and pad compliance are used; without it
    Eq. 23 is unscaled (N^2) and the compliance is the config fallback. ``kappa`` / ``psi_lim``
    default to ``config/model_learner_node.yaml`` (``train.kappa``, ``train.psi_lim_mm``).
    """
    kappa = _train_default("kappa") if kappa is None else kappa
    psi_lim = _train_default("psi_lim_mm") if psi_lim is None else psi_lim
    scale = None if predictor is None else predictor.out_std
    loss = mse_loss(pred, batch.target, scale)
    if use_pene and kappa > 0:
        psi = (predictor.psi_from_force(pred[:, 1]) if predictor is not None
               else _train_default("pad_compliance_mm_per_n") * pred[:, 1])
        loss = loss + kappa * pene_loss(psi, psi_lim)
    return loss
