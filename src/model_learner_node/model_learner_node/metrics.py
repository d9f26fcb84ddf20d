"""Model evaluation: RMSE (Eq. 39) and Corr (Eq. 40) per force channel."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from peel_model.windows import Windows, stack_windows

CHANNELS: tuple[str, ...] = ("fx", "fz")


def rmse(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Eq. 39: sqrt(mean((y - y_hat)^2))."""
    y, y_hat = np.asarray(y, dtype=np.float64), np.asarray(y_hat, dtype=np.float64)
    return float(np.sqrt(np.mean((y - y_hat) ** 2)))


def corr(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Eq. 40: Cov(y, y_hat) / sqrt(Var(y) Var(y_hat)); NaN if either is constant."""
    y, y_hat = np.asarray(y, dtype=np.float64), np.asarray(y_hat, dtype=np.float64)
    vy, vh = y.var(), y_hat.var()
    if vy <= 0 or vh <= 0:
        return float("nan")
    return float(np.mean((y - y.mean()) * (y_hat - y_hat.mean())) / np.sqrt(vy * vh))


@torch.no_grad()
def predict_windows(predictor, win: Windows, batch: int = 8192) -> np.ndarray:
    """Predictions ``[N, 2]`` (N) for every window."""
    dev = next(predictor.buffers()).device
    out = []
    for i in range(0, len(win), batch):
        h = torch.as_tensor(win.hist[i : i + batch], dtype=torch.float32, device=dev)
        v = torch.as_tensor(win.v_next[i : i + batch], dtype=torch.float32, device=dev)
        out.append(predictor(h, v).cpu().numpy())
    return np.concatenate(out).astype(np.float64) if out else np.zeros((0, 2))


def _metrics(win: Windows, pred) -> dict:
    """RMSE and Corr per channel and RMSE over both, of ``pred`` against ``win.f_next``."""
    out = {"rmse": {}, "corr": {}, "n_samples": len(win)}
    for j, ch in enumerate(CHANNELS):
        out["rmse"][ch] = rmse(win.f_next[:, j], pred[:, j])
        out["corr"][ch] = corr(win.f_next[:, j], pred[:, j])
    out["rmse"]["all"] = rmse(win.f_next, pred)
    return out


def evaluate_windows(predictor, win: Windows) -> dict:
    """{"rmse": {fx, fz, all}, "corr": {fx, fz}, "n_samples"} on the given windows."""
    if len(win) == 0:
        raise ValueError("no samples to evaluate")
    was_training = predictor.training
    predictor.eval()
    pred = predict_windows(predictor, win)
    predictor.train(was_training)
    return _metrics(win, pred)


def evaluate(predictor, trajectories: Sequence, pad_front: int | None = None) -> dict:
    """RMSE / Corr per channel over every window of ``trajectories`` (:func:`evaluate_windows`)."""
    return evaluate_windows(predictor, stack_windows(trajectories, predictor.h, pad_front))


def persistence_metrics(win: Windows) -> dict:
    """The same metrics for the trivial predictor F_{k+1} = F_k (a reference, not a model)."""
    pred = win.hist[:, -1, 2:4]
    return _metrics(win, pred)
