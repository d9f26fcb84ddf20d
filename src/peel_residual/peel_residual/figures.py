"""PNG figures of ``peel residual``: each named effect's evidence, the error before and after.

* ``effect_<channel>_<key>.png``: the held-out evidence of one term -- the channel's one-step
  residual with the *other* named terms removed (partial residual), binned over the effect's
  physical variable (mean +- standard error per bin), beside the term's own fitted contribution
  binned the same way. A real effect shows as the two curves running together.
* ``rmse.png``: RMSE per channel, one step and open loop, before and after, held-out tasks.
* ``open_loop_error.png``: RMSE per open-loop step over the planner's horizon.
* ``remains_<channel>.png``: when structure remains, the residual after the correction binned
  over the variable the flexible regressor leans on most.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from peel_model.effect_terms import FORCE_CHANNELS, VELOCITY_CHANNEL

from .data import Steps
from .structure import VARIABLES, state_variables

UNITS = {"fx": "N", "fz": "N", "v": "mm/s"}
_VAR_LABEL = {"q_mm": "q (mm)", "v_mmps": "v (mm/s)", "t_s": "t in the task (s)",
              "dv_mmps": "speed change v_k+1 - v_k (mm/s)",
              "f_other_n": "the other channel's force (N)",
              "v_minus_u_mmps": "v_k - u_k (mm/s)", "u_mmps": "command u_k (mm/s)"}


def variable_values(variable: str, s: Steps, channel: str, dt_s: float) -> np.ndarray:
    """The sample's value of an effect's physical variable (at sample k+1 for forces)."""
    last = s.hist[:, -1]
    if variable == "q_mm":
        return last[:, 0] + s.v_next * dt_s
    if variable == "v_mmps":
        return s.v_next
    if variable == "t_s":
        return s.t_next
    if variable == "dv_mmps":
        return s.v_next - last[:, 1]
    if variable == "f_other_n":
        return last[:, 3 if channel == "fx" else 2]
    if variable == "v_minus_u_mmps":
        return last[:, 1] - s.u
    if variable == "u_mmps":
        return s.u
    raise ValueError(f"unknown variable {variable}")


def _binned(x: np.ndarray, y: np.ndarray, bins: int = 20) -> tuple[np.ndarray, ...]:
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    cx, my, se = [], [], []
    for b in range(len(edges) - 1):
        m = idx == b
        if m.sum() < 3:
            continue
        cx.append(x[m].mean())
        my.append(y[m].mean())
        se.append(y[m].std(ddof=1) / np.sqrt(m.sum()))
    return np.array(cx), np.array(my), np.array(se)


def _save(fig: plt.Figure, path: Path, legend_on: plt.Axes | None = None) -> None:
    """Legend on ``legend_on`` (if given), tight layout, PNG at 110 dpi, figure closed."""
    if legend_on is not None:
        legend_on.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def effect_figure(path: Path, title: str, xlabel: str, unit: str, x: np.ndarray,
                  partial: np.ndarray, contribution: np.ndarray) -> None:
    """Binned partial residual and the term's contribution over the effect's variable."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    cx, my, se = _binned(x, partial)
    ax.errorbar(cx, my, yerr=se, fmt="o", ms=4, capsize=2, label="residual (other terms removed)")
    cx2, my2, _ = _binned(x, contribution)
    ax.plot(cx2, my2, "-", lw=2, label="the term's fitted contribution")
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"one-step residual ({unit})")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rmse_figure(path: Path, before: dict, after: dict) -> None:
    """Grouped bars: channel x mode, before and after."""
    chans = [c for c in (*FORCE_CHANNELS, VELOCITY_CHANNEL) if before.get(c)]
    fig, axes = plt.subplots(1, len(chans), figsize=(3.2 * len(chans), 3.4))
    for ax, ch in zip(np.atleast_1d(axes), chans, strict=True):
        modes = ["one_step", "open_loop"]
        b = [before[ch][m] or 0.0 for m in modes]
        a = [after[ch][m] or 0.0 for m in modes]
        xs = np.arange(len(modes))
        ax.bar(xs - 0.18, b, 0.36, label="before")
        ax.bar(xs + 0.18, a, 0.36, label="after")
        ax.set_xticks(xs, ["one step", "open loop"])
        ax.set_title(f"{ch} ({UNITS[ch]})")
        ax.set_ylabel("RMSE, held-out tasks")
    _save(fig, path, legend_on=np.atleast_1d(axes)[0])


def horizon_figure(path: Path, before: dict, after: dict, dt_s: float) -> None:
    """Open-loop RMSE per horizon step, before and after."""
    chans = [c for c in (*FORCE_CHANNELS, VELOCITY_CHANNEL) if before.get(c)]
    fig, axes = plt.subplots(1, len(chans), figsize=(3.2 * len(chans), 3.4))
    for ax, ch in zip(np.atleast_1d(axes), chans, strict=True):
        b = np.array([np.nan if x is None else x for x in before[ch]])
        a = np.array([np.nan if x is None else x for x in after[ch]])
        t = dt_s * np.arange(1, len(b) + 1)
        ax.plot(t, b, label="before")
        ax.plot(t, a, label="after")
        ax.set_xlabel("open-loop time (s)")
        ax.set_title(f"{ch} ({UNITS[ch]})")
        ax.set_ylabel("RMSE, held-out tasks")
    _save(fig, path, legend_on=np.atleast_1d(axes)[0])


def remains_figure(path: Path, channel: str, s: Steps, resid: np.ndarray,
                   variable: str, r2: float) -> None:
    """The residual after the correction over the variable the flexible regressor uses most."""
    x = state_variables(s)[:, VARIABLES.index(variable)]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    cx, my, se = _binned(x, resid)
    ax.errorbar(cx, my, yerr=se, fmt="o", ms=4, capsize=2)
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel(variable)
    ax.set_ylabel(f"one-step residual after correction ({UNITS[channel]})")
    ax.set_title(f"{channel}: structure no candidate explains (flexible regressor held-out "
                 f"R^2 = {r2:.2f})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def xlabel(variable: str) -> str:
    return _VAR_LABEL.get(variable, variable)


def safe_name(text: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in text)


__all__: list[Any] = ["effect_figure", "horizon_figure", "remains_figure", "rmse_figure",
                      "safe_name", "variable_values", "xlabel"]

