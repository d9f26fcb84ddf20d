"""The settings of ``peel experiment`` and ``peel experiment sweep`` (section 4.4, Table 2): the
``experiment.*`` and ``sweep.*`` groups of config/peel_bringup.yaml, validated, and the arms
``--methods`` accepts."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from peel_msgs_py.errors import PeelError
from peel_msgs_py.params import ParamSpec, load_node_params, validate

NODE = "peel_bringup"
METHODS: tuple[str, ...] = ("ol-mppi", "baseline1", "baseline2")
#: every arm ``--methods`` accepts: the paper's three and OL-MPPI with the fast step
KNOWN_METHODS: tuple[str, ...] = (*METHODS, "ol-mppi-fast")
ORACLE = "oracle"

#: ``experiment.*`` and ``sweep.*`` groups of config/peel_bringup.yaml.
EXPERIMENT_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("experiment.tasks", int, 20, "consecutive peels per method (4.4)", min=1),
    ParamSpec("experiment.methods", list, list(METHODS), "methods to compare (4.4)"),
    ParamSpec("experiment.seeds", list, [0], "experiment seeds"),
    ParamSpec("experiment.oracle", bool, True, "also run the oracle"),
    ParamSpec("experiment.workers", int, 1, "worker processes (results do not depend on it)",
              min=1),
    ParamSpec("experiment.n_samples", int, 50, "MPPI N during the experiment (4.4: 50)", min=1),
    ParamSpec("experiment.horizon", int, 5, "MPPI H during the experiment (Table 2: 5)", min=1),
    ParamSpec("experiment.lambda", float, 0.1, "MPPI lambda (Table 2: 0.1)", min=1e-6),
    ParamSpec("experiment.save_model", bool, True, "save OL-MPPI's last-task model"),
    ParamSpec("sweep.n_values", list, [10, 30, 50, 80, 100], "N values of Table 2"),
    ParamSpec("sweep.h_values", list, [1, 3, 5, 7, 10], "H values of Table 2"),
    ParamSpec("sweep.lambda_values", list, [0.02, 0.05, 0.1, 0.2, 0.5], "lambda values"),
    ParamSpec("sweep.seeds", list, [0, 1, 2], "seeds (one plant substrate each)"),
)


def _int_tuple(name: str, value: Any) -> tuple[int, ...]:
    if not isinstance(value, list | tuple) or not value or not all(
            isinstance(x, int) and not isinstance(x, bool) for x in value):
        raise PeelError(f"parameter '{name}' must be a non-empty list of integers")
    if any(x < 0 for x in value):
        raise PeelError(f"parameter '{name}' entries must be >= 0")
    return tuple(int(x) for x in value)


def _float_tuple(name: str, value: Any) -> tuple[float, ...]:
    if not isinstance(value, list | tuple) or not value or not all(
            isinstance(x, int | float) and not isinstance(x, bool) for x in value):
        raise PeelError(f"parameter '{name}' must be a non-empty list of numbers")
    out = tuple(float(x) for x in value)
    if any(not math.isfinite(x) or x <= 0 for x in out):
        raise PeelError(f"parameter '{name}' entries must be finite and > 0")
    return out


@dataclass(frozen=True)
class ExperimentConfig:
    """The ``experiment.*`` and ``sweep.*`` parameters of config/peel_bringup.yaml."""

    tasks: int = 20
    methods: tuple[str, ...] = METHODS
    seeds: tuple[int, ...] = (0,)
    oracle: bool = True
    workers: int = 1
    n_samples: int = 50
    horizon: int = 5
    lam: float = 0.1
    save_model: bool = True
    sweep_n: tuple[int, ...] = (10, 30, 50, 80, 100)
    sweep_h: tuple[int, ...] = (1, 3, 5, 7, 10)
    sweep_lambda: tuple[float, ...] = (0.02, 0.05, 0.1, 0.2, 0.5)
    sweep_seeds: tuple[int, ...] = (0, 1, 2)
    #: plant severity level (None: ``plant.level`` of the simulator config), docs/simulator.md
    plant_level: int | None = None
    #: how the process changes over the peels: stationary, drift or batch-switch
    sequence: str = "stationary"

    @classmethod
    def from_params(cls, flat: Mapping[str, Any]) -> ExperimentConfig:
        mine = {k: v for k, v in flat.items() if k.startswith(("experiment.", "sweep."))}
        p = validate(EXPERIMENT_SPECS, mine)
        methods = tuple(str(m) for m in p["experiment.methods"])
        check_methods(methods)
        cfg = cls(
            tasks=p["experiment.tasks"], methods=methods,
            seeds=_int_tuple("experiment.seeds", p["experiment.seeds"]),
            oracle=p["experiment.oracle"], workers=p["experiment.workers"],
            n_samples=p["experiment.n_samples"], horizon=p["experiment.horizon"],
            lam=p["experiment.lambda"], save_model=p["experiment.save_model"],
            sweep_n=_int_tuple("sweep.n_values", p["sweep.n_values"]),
            sweep_h=_int_tuple("sweep.h_values", p["sweep.h_values"]),
            sweep_lambda=_float_tuple("sweep.lambda_values", p["sweep.lambda_values"]),
            sweep_seeds=_int_tuple("sweep.seeds", p["sweep.seeds"]),
        )
        if min(cfg.sweep_n) < 1 or min(cfg.sweep_h) < 1:
            raise PeelError("parameter 'sweep.n_values'/'sweep.h_values' entries must be >= 1")
        return cfg


def load_experiment_config(overrides: str | os.PathLike[str] | None = None
                           ) -> ExperimentConfig:
    """``config/peel_bringup.yaml`` (+ an override file)."""
    return ExperimentConfig.from_params(load_node_params(NODE, overrides))


def check_methods(methods: Sequence[str]) -> None:
    """Raise PeelError unless every method is known and none repeats."""
    if not methods:
        raise PeelError("parameter 'methods' must name at least one method")
    for m in methods:
        if m not in KNOWN_METHODS:
            raise PeelError(f"parameter 'methods': unknown method {m!r} (known: "
                            f"{', '.join(KNOWN_METHODS)})")
    if len(set(methods)) != len(methods):
        raise PeelError("parameter 'methods' names a method twice")
