"""Checking a forward-model checkpoint before the planner plans with it (docs/graph.md, "The
model swap"): no ROS here, so the checks are tested without DDS.

:func:`validate_model` loads the safetensors checkpoint with
:func:`~model_learner_node.checkpoint.load_checkpoint` (format, architecture, tensor names,
shapes, dtypes, checksum, finite values; never a pickle), compares its history length ``h``
with the running model's, and runs a probe batch built from the latest measured rows; the
outputs must be finite. Any failure raises :class:`~peel_msgs_py.errors.PeelError` with the
reason, which the planner node returns as the refusal of the swap.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from peel_msgs_py.errors import CheckpointError

_VERSION_RE = re.compile(r"model_v(\d+)")
#: A probe row (q_mm, v_mmps, fx_N, fz_N) before the first measured sample.
DEFAULT_ROW = (5.0, 1.0, 2.0, 2.0)


def resolve_model_path(value: str) -> Path:
    """``model.path``: empty = the shipped checkpoint."""
    from model_learner_node.checkpoint import shipped_checkpoint

    return shipped_checkpoint() if not value else Path(value)


def version_of(path: Path, fallback: int) -> int:
    """Model version from a ``model_vNNNN`` file name, else ``fallback``."""
    m = _VERSION_RE.search(path.name)
    return int(m.group(1)) if m else fallback


def probe_batch(rows: np.ndarray | None, h: int, batch: int, dtype: torch.dtype
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """``batch`` copies of the last ``h`` rows (padded with the first) and speeds 0-8 mm/s."""
    if rows is None or len(rows) == 0:
        rows = np.array([DEFAULT_ROW])
    rows = rows[-h:]
    if len(rows) < h:
        rows = np.concatenate([np.repeat(rows[:1], h - len(rows), axis=0), rows])
    hist = torch.as_tensor(rows, dtype=dtype).expand(batch, h, 4).clone()
    return hist, torch.linspace(0.0, 8.0, batch, dtype=dtype)


def validate_model(path: Path, probe_rows: np.ndarray | None, batch: int, h_ref: int | None) -> Any:
    """Load and check a checkpoint; returns the predictor or raises PeelError (module doc).

    ``probe_rows``: measured rows (q_mm, v_mmps, fx_N, fz_N) of the current task, or None.
    """
    from model_learner_node.checkpoint import load_checkpoint

    if path.suffix not in (".safetensors", ""):
        raise CheckpointError(f"model.path must name a .safetensors checkpoint, got {path.name}")
    pred = load_checkpoint(path)
    h = int(pred.h)
    if h_ref is not None and h != h_ref:
        raise CheckpointError(f"model history h = {h} differs from the running model's {h_ref}")
    hist, v_next = probe_batch(probe_rows, h, batch, next(pred.parameters()).dtype)
    with torch.inference_mode():
        out = pred.predict(hist, v_next)
    if tuple(out.shape) != (batch, 2):
        raise CheckpointError(f"probe batch: model output has shape {tuple(out.shape)}, "
                              f"expected {(batch, 2)}")
    if not bool(torch.isfinite(out).all()):
        raise CheckpointError("probe batch: the model predicts non-finite forces")
    return pred
