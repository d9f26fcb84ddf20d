"""Is a forward model usable? Finite outputs on a probe batch (shared by planner and learner).

:func:`~peel_model.checkpoint.load_checkpoint` refuses non-finite *weights*, but finite
weights can still give non-finite forces (weights scaled by 1e30 overflow float32 in the first
layers). A model is usable only if it predicts finite (F_RX, F_RZ) at the next sample (Eq. 1-2)
for a probe batch: the latest measured rows when there are any, else a fixed synthetic history,
with next velocities spread over 0..8 mm/s (and, for a model with a compensation term, sample
times over 0..60 s and its speed response). :func:`check_finite_outputs` runs that probe; the
planner runs it before a model swap, the learner on its starting model and on every MAML result
before it is offered to the planner, ``python -m model_learner_node.evaluate`` before scoring.
"""

from __future__ import annotations

import numpy as np
import torch

from peel_msgs_py.errors import CheckpointError

#: The synthetic probe row (q_mm, v_mmps, fx_N, fz_N) used before any measured sample exists.
PROBE_ROW = (5.0, 1.0, 2.0, 2.0)
#: Time in the task (s) up to which a model's time terms are probed (t_max of section 4.2).
PROBE_T_MAX_S = 60.0


def probe_batch(h: int, rows: np.ndarray | None = None, batch: int = 16,
                dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """``(hist[batch, h, 4], v_next[batch])``: the last ``h`` rows (the first one repeated when
    there are fewer), the same history for every row of the batch."""
    if rows is None or len(rows) == 0:
        rows = np.array([PROBE_ROW])
    rows = np.asarray(rows, dtype=np.float64)[-h:]
    if len(rows) < h:
        rows = np.concatenate([np.repeat(rows[:1], h - len(rows), axis=0), rows])
    hist = torch.as_tensor(rows, dtype=dtype).expand(batch, h, 4).clone()
    return hist, torch.linspace(0.0, 8.0, batch, dtype=dtype)


def check_finite_outputs(predictor: torch.nn.Module, rows: np.ndarray | None = None,
                         batch: int = 16, what: str = "the model") -> None:
    """Raise :class:`CheckpointError` unless ``predictor`` gives finite forces of shape
    ``(batch, 2)`` on the probe batch (module docstring)."""
    param = next(predictor.parameters())
    hist, v_next = probe_batch(int(predictor.h), rows, batch, param.dtype)
    hist, v_next = hist.to(param.device), v_next.to(param.device)
    # a model with a compensation term (docs/residual.md): its time terms over a task's span,
    # its speed response for the probe's commands
    extra = {}
    if getattr(predictor, "needs_time", False):
        extra["t_next"] = torch.linspace(0.0, PROBE_T_MAX_S, batch, dtype=param.dtype,
                                         device=param.device)
    with torch.inference_mode():
        out = predictor.predict(hist, v_next, **extra)
        speed = getattr(predictor, "speed", None)
        if callable(speed) and getattr(predictor, "velocity_terms", None):
            v = speed(v_next, hist[:, -1, 1])
            if not bool(torch.isfinite(v).all()):
                raise CheckpointError(f"probe batch: {what} gives non-finite speeds from its "
                                      "speed response")
    if tuple(out.shape) != (batch, 2):
        raise CheckpointError(f"probe batch: {what} outputs shape {tuple(out.shape)}, expected "
                              f"{(batch, 2)}")
    bad = int((~torch.isfinite(out)).sum())
    if bad:
        raise CheckpointError(f"probe batch: {what} predicts non-finite forces ({bad} of "
                              f"{out.numel()} outputs are NaN or infinite)")
