"""Checking a forward-model checkpoint before the planner plans with it (docs/graph.md, "The
model swap"): no ROS here, so the checks are tested without DDS.

:func:`validate_model` loads the safetensors checkpoint with
:func:`~peel_model.checkpoint.load_checkpoint` (format, architecture, tensor names,
shapes, dtypes, checksum, finite values; never a pickle), compares its history length ``h``
with the running model's, and runs the probe batch of
:func:`~peel_model.validation.check_finite_outputs` (the check the learner runs on its
own starting model and updates) on the latest measured rows; the forces (Eq. 1-2) must be
finite. Any failure raises
:class:`~peel_msgs_py.errors.PeelError` with the reason, which the planner node returns as the
refusal of the swap. Versions are not taken from file names: the planner's
:class:`~peel_model.versions.ModelLedger` allocates them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.errors import CheckpointError


def resolve_model_path(value: str) -> Path:
    """``model.path``: empty = the shipped checkpoint."""
    from peel_model.checkpoint import shipped_checkpoint

    return shipped_checkpoint() if not value else Path(value)


def validate_model(path: Path, probe_rows: np.ndarray | None, batch: int, h_ref: int | None) -> Any:
    """Load and check a checkpoint; returns the predictor or raises PeelError (module doc).

    ``probe_rows``: measured rows (q_mm, v_mmps, fx_N, fz_N) of the current task, or None.
    """
    from peel_model.checkpoint import load_checkpoint
    from peel_model.validation import check_finite_outputs

    if path.suffix not in (".safetensors", ""):
        raise CheckpointError(f"model.path must name a .safetensors checkpoint, got {path.name}")
    pred = load_checkpoint(path)
    h = int(pred.h)
    if h_ref is not None and h != h_ref:
        raise CheckpointError(f"model history h = {h} differs from the running model's {h_ref}")
    check_finite_outputs(pred, probe_rows, batch, what=path.name)
    return pred
