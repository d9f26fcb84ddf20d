"""The ``residual:`` group of config/peel_residual.yaml as parameter specs (no torch).

Registered as the ``peel_residual`` section under the ``peel.parameters`` entry point, so that
every parameter file naming them is checked by name and type, as for ``train.*``; read by
``peel residual`` (:mod:`.config`). Not paper constants: settings of the analysis
(docs/residual.md). The shape-parameter lists are the grids of the candidate library
(:mod:`peel_model.effect_terms`).
"""

from __future__ import annotations

from peel_msgs_py.params import ParamSpec

#: The candidate families, in the order of the library (``effect_terms.FAMILIES``).
FAMILY_NAMES: tuple[str, ...] = (
    "sensor_offset", "viscous_drag", "quadratic_drag", "coulomb_friction", "stribeck_friction",
    "periodic_adhesion", "near_start_hold", "position_trend", "decay_in_time", "drift_in_time",
    "hysteresis", "cross_talk", "actuator_lag", "speed_scale", "speed_offset",
)

#: ``residual.<name>`` -> (the family whose shape parameter it lists, the shipped grid).
GRIDS: dict[str, tuple[str, list[float]]] = {
    "coulomb_v0_mmps": ("coulomb_friction", [0.2]),
    "stribeck_vs_mmps": ("stribeck_friction", [0.5, 1.0, 2.0]),
    "periodic_lambda_mm": ("periodic_adhesion", [2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.5]),
    "near_start_length_mm": ("near_start_hold", [1.0, 2.0, 4.0, 8.0]),
    "decay_tau_s": ("decay_in_time", [1.0, 2.0, 5.0, 10.0, 20.0]),
    "hysteresis_dv0_mmps": ("hysteresis", [0.3]),
}

RESIDUAL_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("residual.holdout", float, 0.3, "share of tasks held out of the fit", min=0.05,
              max=0.9),
    ParamSpec("residual.seed", int, 0, "seed of the split, the bootstrap, the structure check",
              min=0),
    ParamSpec("residual.folds", int, 5, "cross-validation folds (by task)", min=2, max=50),
    ParamSpec("residual.horizon_steps", int, 0,
              "open-loop model steps; 0 = the planner's mppi.horizon x steps_per_horizon_step",
              min=0, max=1000),
    ParamSpec("residual.stride", int, 5, "samples between open-loop starts", min=1),
    ParamSpec("residual.min_explained", float, 0.03,
              "least held-out share of its channel's residual variance a named term explains",
              min=0.0, max=1.0),
    ParamSpec("residual.ci_level", float, 0.95, "coefficient confidence level", min=0.5,
              max=0.999),
    ParamSpec("residual.bootstrap", int, 200, "bootstrap resamples by task", min=20),
    ParamSpec("residual.min_structure", float, 0.05,
              "held-out R^2 of a flexible regressor above which structure remains", min=0.0,
              max=1.0),
    ParamSpec("residual.drift_alpha", float, 0.01,
              "significance of the per-task residual's slope over the task order (drift across "
              "tasks)", min=1e-6, max=0.5),
    ParamSpec("residual.open_loop_fit", bool, False,
              "also fit the candidates to the open-loop residual over the planner's horizon "
              "(output error), after the one-step fit; more power, more false alarms "
              "(docs/residual.md)"),
    ParamSpec("residual.open_loop_fit_steps", int, 0,
              "model steps of each output-error run; 0 = the planner's horizon", min=0, max=1000),
    ParamSpec("residual.open_loop_fit_stride", int, 10, "samples between output-error starts",
              min=1),
    ParamSpec("residual.heldout_alpha", float, 0.0,
              "0: off; else a kept term must lower the held-out open-loop error consistently "
              "across the held-out tasks (Wilcoxon, Holm, at this level; needs >= 5 of them)",
              min=0.0, max=0.5),
    ParamSpec("residual.families", list, list(FAMILY_NAMES), "candidate families"),
    *(ParamSpec(f"residual.{name}", list, list(grid), f"shape parameters of {fam}")
      for name, (fam, grid) in GRIDS.items()),
)
