"""Settings of ``peel residual``: the ``residual:`` group of config/peel_residual.yaml
(specs in :mod:`.params`), validated into a :class:`ResidualConfig` with its candidates."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from peel_model.effect_terms import FAMILIES, Candidate, candidates_from_grid
from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import load_node_params, validate_group

from .params import GRIDS, RESIDUAL_SPECS

NODE = "peel_residual"


@dataclass(frozen=True)
class ResidualConfig:
    """Validated ``residual.*`` settings; :attr:`candidates` is the candidate library."""

    holdout: float = 0.3
    seed: int = 0
    folds: int = 5
    horizon_steps: int = 25
    stride: int = 5
    min_explained: float = 0.03
    ci_level: float = 0.95
    bootstrap: int = 200
    min_structure: float = 0.05
    drift_alpha: float = 0.01
    open_loop_fit: bool = False
    open_loop_fit_steps: int = 0
    open_loop_fit_stride: int = 10
    heldout_alpha: float = 0.0
    candidates: tuple[Candidate, ...] = ()

    @classmethod
    def from_params(cls, flat: Mapping[str, Any], planner_flat: Mapping[str, Any] | None = None
                    ) -> ResidualConfig:
        p = validate_group(RESIDUAL_SPECS, flat, "residual", strip=True)
        families = [str(f) for f in p["families"]]
        unknown = [f for f in families if f not in FAMILIES]
        if unknown or not families:
            raise ParameterError(f"parameter 'residual.families': unknown or empty {unknown} "
                                 f"(known: {', '.join(FAMILIES)})")
        grid: dict[str, list[float] | None] = {f: None for f in families}
        for name, (fam, _) in GRIDS.items():
            values = p[name]
            if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and x > 0
                       for x in values):
                raise ParameterError(f"parameter 'residual.{name}' must list positive numbers")
            if fam in grid:
                if not values:
                    raise ParameterError(f"parameter 'residual.{name}' is empty but "
                                         f"'{fam}' is a candidate family")
                grid[fam] = [float(x) for x in values]
        horizon = p["horizon_steps"]
        if horizon == 0:
            pf = planner_flat if planner_flat is not None else load_node_params("peel_planner_node")
            horizon = int(pf.get("mppi.horizon", 5)) * int(pf.get("mppi.steps_per_horizon_step", 5))
        return cls(holdout=p["holdout"], seed=p["seed"], folds=p["folds"],
                   horizon_steps=horizon, stride=p["stride"], min_explained=p["min_explained"],
                   ci_level=p["ci_level"], bootstrap=p["bootstrap"],
                   min_structure=p["min_structure"], drift_alpha=p["drift_alpha"],
                   open_loop_fit=p["open_loop_fit"],
                   open_loop_fit_steps=p["open_loop_fit_steps"],
                   open_loop_fit_stride=p["open_loop_fit_stride"],
                   heldout_alpha=p["heldout_alpha"],
                   candidates=tuple(candidates_from_grid(grid)))


def load_residual_config(overrides: str | None = None, **changes: Any) -> ResidualConfig:
    """The shipped ``residual:`` group (+ an override file, + keyword changes); the open-loop
    horizon from the planner's parameters (shipped + the same override file)."""
    flat = load_node_params(NODE, overrides)
    flat.update({f"residual.{k}": v for k, v in changes.items()})
    return ResidualConfig.from_params(flat, load_node_params("peel_planner_node", overrides))
