"""The planner's health for ``/diagnostics`` (ROS-free; :mod:`peel_msgs_py.diagnostics`).

Levels: ERROR when the median ``plan()`` (Algorithm 2) of the last plans takes longer than the
control period (0.5 s, section 4.2: the commands would be late on a real robot); WARN when one of
them did (a late command), or while the last model swap asked for was refused (the planner plans
on with its last good model); OK otherwise. The margins are the 20 N prewarning (4.2) less the
onset of the planning barrier (``cost.barrier.start_n``) and less the current task's peak |F|.
The last plan's cost per term (:func:`plan_costs`) shows which critic drives the command.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from peel_msgs_py.diagnostics import ERROR, WARN, Check, DurationWindow, Status, make_status, ms
from peel_msgs_py.modelinfo import ModelRecord

from .config import PlannerConfig


def peak_force(rows: Sequence[Sequence[float]]) -> float | None:
    """Largest |F_RX| or |F_RZ| of a task's rows (t, q, v, u, fx, fz, psi); None when empty."""
    return max((max(abs(r[4]), abs(r[5])) for r in rows), default=None)


#: Prefix of the key values that hold the last plan's cost per term (:func:`plan_costs`).
PLAN_COST = "plan cost "


def plan_costs(last: Mapping[str, Any]) -> dict[str, float]:
    """The last plan's cost per critic (``cost.<name>``) and its control cost (Eq. 38's control
    term), each the omega-weighted mean over the sampled sequences (omega of Eq. 38): what the
    samples behind the new U (Eq. 31) cost, term by term. {} before the first plan
    (``last`` is :attr:`~peel_planner_node.mppi.Planner.last`)."""
    if "omega" not in last:
        return {}
    omega = last["omega"].double()
    out = {name: float(omega @ v.double()) for name, v in last["terms"].items()}
    out["control"] = float(omega @ last["control"].double())
    return out


def planner_status(latency: DurationWindow, cfg: PlannerConfig, model: ModelRecord,
                   refusal: str | None, refusals: int, peak_n: float | None,
                   error_margin_n: float = 0.0,
                   costs: Mapping[str, float] | None = None) -> Status:
    """plan() latency against the control period, late commands, the model and the margins
    (``error_margin_n``: the guard's margin from the model's measured force error, Eq. M1);
    ``costs``: the last plan's cost per term (:func:`plan_costs`)."""
    median, worst, late = latency.summary()
    period = latency.budget_s or 0.0
    checks: list[Check] = []
    if median is not None and median > period:
        checks.append((ERROR, f"plan() median {ms(median):.0f} ms over the "
                              f"{ms(period):.0f} ms control period"))
    elif late:
        checks.append((WARN, f"{late} of the last {len(latency.recent)} plans over the "
                             f"{ms(period):.0f} ms control period (late commands)"))
    if refusal:
        checks.append((WARN, refusal))
    prewarn = cfg.safety.f_prewarn_n
    values: dict[str, object] = {
        "model version": model.version, "model sha256": model.sha256[:12],
        "model producer": model.producer, "model task": model.task,
        "plans": latency.count, "plan latency median (ms)": ms(median),
        "plan latency max (ms)": ms(worst), "latency window (plans)": len(latency.recent),
        "control period (ms)": ms(period), "late commands": latency.over,
        "swaps refused": refusals, "last refusal": refusal,
        "prewarning (N)": prewarn, "barrier onset (N)": cfg.cost.barrier.start_n,
        "planning margin (N)": prewarn - cfg.cost.barrier.start_n,
        "task margin (N)": None if peak_n is None else prewarn - peak_n,
        "model-error margin (N)": error_margin_n,
        "N": cfg.mppi.n_samples, "H": cfg.mppi.horizon,
        **{PLAN_COST + name: value for name, value in (costs or {}).items()},
    }
    return make_status("peel_planner_node: planning", "peel_planner_node", checks, values,
                       ok_message=f"planning with model v{model.version}")
