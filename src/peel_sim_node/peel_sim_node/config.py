"""Simulator configuration: the ``peel_sim_node`` parameters as a validated, typed object.

Every constant lives in ``config/peel_sim_node.yaml`` (commented with its equation / section);
this module declares the same names as :class:`~peel_msgs_py.params.ParamSpec` and turns a flat
parameter dict into a :class:`SimConfig` whose groups read like the YAML
(``cfg.task.q_ter_mm``, ``cfg.randomization.friction_low``, ...).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

from peel_bridge.slowdown import SlowdownParams, SlowdownZone, slowdown_specs
from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import ParamSpec, load_node_params, validate

NODE = "peel_sim_node"
#: Parameter group of the ROS node wrapper, ignored by the library.
NODE_GROUP = "node."

F, INT, B = float, int, bool

#: (name, type, default, min, max, description). Defaults equal the shipped YAML.
_TABLE: list[tuple[str, type, Any, float | None, float | None, str]] = [
    ("task.q_ter_mm", F, 25.0, None, None, "goal position q_ter, mm (4.1)"),
    ("task.t_max_s", F, 60.0, None, None, "t_max, s (4.2)"),
    ("task.dt_s", F, 0.1, 1e-3, 1.0, "sample period, s (4.2)"),
    ("task.control_period_s", F, 0.5, 1e-3, 10.0, "control period, s (4.2)"),
    ("task.f_prewarn_n", F, 20.0, 0.0, None, "force prewarning, N (4.2)"),
    ("scene.substeps", INT, 10, 1, 1000, "PyBullet steps per sample"),
    ("scene.blade_mass_kg", F, 1.0, 1e-3, None, "blade + tool mass, kg"),
    ("scene.coupling_stiffness_n_per_mm", F, 3.0, 1e-3, None, "robot-blade compliance, N/mm"),
    ("scene.coupling_damping_ns_per_mm", F, 0.02, 0.0, None, "compliance damping, N s/mm"),
    ("scene.press_depth_mm", F, 0.725, 0.0, 5.0, "tool depth the robot holds, mm"),
    ("scene.tool_compliance_z_mm_per_n", F, 0.2, 0.0, 10.0,
     "vertical compliance of blade + wrist, mm/N (0 = rigid)"),
    ("scene.blade_contact_length_mm", F, 4.0, 0.1, None, "blade footprint, mm"),
    ("scene.blade_thickness_mm", F, 0.5, 0.01, None, "substrate lift at the blade, mm"),
    ("scene.tile_length_mm", F, 5.0, 0.1, None, "pad tile length, mm"),
    ("scene.n_tiles", INT, 12, 1, 1000, "number of pad tiles"),
    ("scene.substrate_mass_kg", F, 0.05, 1e-4, None, "substrate mass, kg"),
    ("scene.substrate_contact_stiffness", F, 2e5, 0.0, None, "blade-glass stiffness, N/m"),
    ("scene.substrate_contact_damping", F, 200.0, 0.0, None, "blade-glass damping, N s/m"),
    ("scene.glass_friction", F, 0.7, 0.0, 10.0, "blade-glass friction coefficient"),
    ("scene.static_friction_ratio", F, 1.35, 1.0, 10.0, "mu_static / mu_kinetic"),
    ("scene.stick_speed_mmps", F, 0.3, 0.0, None, "sticking threshold, mm/s"),
    ("load.base_n", F, 2.5, 0.0, None, "hold-down load at rest, N"),
    ("load.rate_gain", F, 0.8, 0.0, None, "peel-rate load gain"),
    ("load.rate_ref_mmps", F, 2.5, 1e-3, None, "reference peel speed, mm/s"),
    ("load.rate_exponent", F, 1.5, 0.0, 5.0, "peel-rate exponent n"),
    ("load.rate_tau_s", F, 1.0, 1e-3, None, "peel-front relaxation time, s"),
    ("randomization.friction_low", F, 0.6, 0.0, 10.0, "pad friction low (3.2.1)"),
    ("randomization.friction_high", F, 1.0, 0.0, 10.0, "pad friction high (3.2.1)"),
    ("randomization.stiffness_low", F, 8000.0, 0.0, None, "pad stiffness low, N/m (3.2.1)"),
    ("randomization.stiffness_high", F, 16000.0, 0.0, None, "pad stiffness high, N/m (3.2.1)"),
    ("randomization.damping_low", F, 600.0, 0.0, None, "pad damping low, N s/m (3.2.1)"),
    ("randomization.damping_high", F, 1400.0, 0.0, None, "pad damping high, N s/m (3.2.1)"),
    ("randomization.tile_spread", F, 0.2, 0.0, 0.95, "local adhesion spread"),
    ("compensation.enabled", B, True, None, None, "add Eq. 21-22"),
    ("compensation.youngs_modulus_n_per_mm2", F, 70000.0, 0.0, None, "E, N/mm^2 (Eq. 19)"),
    ("compensation.width_mm", F, 2.0, 0.0, None, "b, mm (Eq. 18-19)"),
    ("compensation.thickness_mm", F, 0.5, 0.0, None, "h, mm (Eq. 18-19)"),
    ("compensation.alpha_deg", F, 30.0, 0.0, 90.0, "alpha, deg (Eq. 21-22)"),
    ("compensation.peeled_length_0_mm", F, 15.0, 1e-3, None, "L_p at C, mm (Eq. 19)"),
    ("compensation.phi_unit_deg", B, True, None, None, "Eq. 20 phi in degrees"),
    ("noise.velocity_sigma_mmps", F, 0.15, 0.0, None, "actuator scatter Sigma, mm/s (Eq. 2)"),
    ("noise.force_resolution_n", F, 0.01, 0.0, None, "sensor resolution, N (4.1)"),
    ("noise.force_sigma_n", F, 0.05, 0.0, None, "white sensor noise, N"),
    ("noise.force_bias_sigma_n", F, 0.05, 0.0, None, "per-task sensor bias, N"),
    ("plant.level", INT, 3, 0, 3, "plant severity level of source=plant (0 = simulator)"),
    ("plant.friction_low", F, 0.75, 0.0, 10.0, "plant pad friction low"),
    ("plant.friction_high", F, 0.95, 0.0, 10.0, "plant pad friction high"),
    ("plant.stiffness_low", F, 8000.0, 0.0, None, "plant stiffness low, N/m"),
    ("plant.stiffness_high", F, 12500.0, 0.0, None, "plant stiffness high, N/m"),
    ("plant.damping_low", F, 500.0, 0.0, None, "plant damping low, N s/m"),
    ("plant.damping_high", F, 900.0, 0.0, None, "plant damping high, N s/m"),
    ("plant.residual_vacuum_n", F, 2.0, 0.0, None, "residual vacuum load, N"),
    ("plant.residual_length_mm", F, 4.0, 1e-3, None, "residual vacuum decay length, mm"),
    ("plant.actuator_lag_s", F, 0.15, 0.0, None, "actuator lag, s"),
    ("plant.drift_n_per_sqrt_s", F, 0.08, 0.0, None, "sensor drift, N/sqrt(s)"),
    ("plant_l2.friction_low", F, 0.75, 0.0, 10.0, "level-2 pad friction low"),
    ("plant_l2.friction_high", F, 0.95, 0.0, 10.0, "level-2 pad friction high"),
    ("plant_l2.stiffness_low", F, 8000.0, 0.0, None, "level-2 stiffness low, N/m"),
    ("plant_l2.stiffness_high", F, 12500.0, 0.0, None, "level-2 stiffness high, N/m"),
    ("plant_l2.damping_low", F, 300.0, 0.0, None, "level-2 damping low, N s/m"),
    ("plant_l2.damping_high", F, 600.0, 0.0, None, "level-2 damping high, N s/m"),
    ("plant_l2.base_load_scale", F, 1.0, 0.0, 10.0, "level-2 static hold-down x load.base_n"),
    ("plant_l2.rate_gain_scale", F, 0.35, 0.0, 10.0, "level-2 peel-rate load x load.rate_gain"),
    ("plant_l3.friction_low", F, 0.55, 0.0, 10.0, "level-3 (wet) pad friction low"),
    ("plant_l3.friction_high", F, 0.7, 0.0, 10.0, "level-3 (wet) pad friction high"),
    ("plant_l3.static_friction_ratio", F, 1.15, 1.0, 10.0, "level-3 mu_static / mu_kinetic"),
    ("plant_l3.base_load_scale", F, 2.0, 0.0, 10.0, "level-3 capillary hold x level-2 static load"),
    ("plant_l3.actuator_lag_s", F, 0.35, 0.0, 5.0, "level-3 actuator lag, s"),
    ("sequence.drift_friction_per_task", F, 0.015, -0.5, 0.5,
     "pad wear: relative friction rise per peel (drift)"),
    ("sequence.switch_task", INT, 11, 1, None, "first task on the new pad batch (batch-switch)"),
    ("sequence.switch_stiffness_scale", F, 1.2, 0.01, 100.0, "new batch: x stiffness"),
    ("sequence.switch_damping_scale", F, 1.5, 0.01, 100.0, "new batch: x damping"),
    ("sequence.switch_friction_scale", F, 1.15, 0.01, 100.0, "new batch: x friction"),
    ("dataset.param_sets", INT, 20, 1, None, "K parameter sets"),
    ("dataset.per_set", INT, 10, 1, None, "M trajectories per set"),
    ("dataset.seed", INT, 0, 0, None, "dataset seed"),
    ("dataset.workers", INT, 2, 1, 256, "worker processes"),
    ("dataset.u_min_mmps", F, 0.5, 0.0, None, "exploration speed min, mm/s"),
    ("dataset.u_max_mmps", F, 8.0, 0.0, None, "exploration speed max, mm/s"),
]

SPECS: list[ParamSpec] = [
    ParamSpec(name, typ, default, desc, mn, mx) for name, typ, default, mn, mx, desc in _TABLE
] + list(slowdown_specs("safety"))  # Eq. M6, the bridge's slowdown zone (peel_bridge.slowdown)

#: Intervals [low, high] that must not be inverted.
_INTERVALS = [
    ("randomization.friction", "_low", "_high"),
    ("randomization.stiffness", "_low", "_high"),
    ("randomization.damping", "_low", "_high"),
    ("plant.friction", "_low", "_high"),
    ("plant.stiffness", "_low", "_high"),
    ("plant.damping", "_low", "_high"),
    ("plant_l2.friction", "_low", "_high"),
    ("plant_l2.stiffness", "_low", "_high"),
    ("plant_l2.damping", "_low", "_high"),
    ("plant_l3.friction", "_low", "_high"),
    ("dataset.u", "_min_mmps", "_max_mmps"),
]


class _Group:
    """Read-only attribute view of one parameter group (``task``, ``scene``, ...)."""

    def __init__(self, values: dict[str, Any]) -> None:
        object.__setattr__(self, "_values", dict(values))

    def __getattr__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("SimConfig groups are read-only")

    def __repr__(self) -> str:
        return f"_Group({self._values!r})"


@dataclass(frozen=True)
class SimConfig:
    """Validated simulator parameters; ``flat`` holds the dotted names of the YAML."""

    flat: dict[str, Any]

    def __getattr__(self, group: str) -> _Group:
        if group.startswith("_") or group == "flat":
            raise AttributeError(group)
        prefix = group + "."
        vals = {k[len(prefix):]: v for k, v in self.flat.items() if k.startswith(prefix)}
        if not vals:
            raise AttributeError(group)
        return _Group(vals)

    @property
    def samples_per_control(self) -> int:
        """Samples per control period (5 in the paper)."""
        return round(self.task.control_period_s / self.task.dt_s)

    @classmethod
    def from_params(cls, flat: dict[str, Any]) -> SimConfig:
        """Validate a flat parameter dict (dotted names); unknown names or bad values raise
        :class:`~peel_msgs_py.errors.ParameterError` naming the parameter."""
        # ``node.*`` belongs to the ROS node (docs/graph.md), not to the simulator library
        vals = validate(SPECS, {k: v for k, v in flat.items() if not k.startswith(NODE_GROUP)})
        if vals["task.q_ter_mm"] <= 0.0:
            raise ParameterError(
                f"parameter 'task.q_ter_mm' must be > 0, got {vals['task.q_ter_mm']!r}"
            )
        if vals["task.t_max_s"] <= 0.0:
            raise ParameterError(f"parameter 'task.t_max_s' must be > 0, got {vals['task.t_max_s']!r}")
        for base, lo, hi in _INTERVALS:
            if vals[base + lo] > vals[base + hi]:
                raise ParameterError(
                    f"parameter '{base + lo}' = {vals[base + lo]!r} is above "
                    f"'{base + hi}' = {vals[base + hi]!r} (inverted interval)"
                )
        ratio = vals["task.control_period_s"] / vals["task.dt_s"]
        if abs(ratio - round(ratio)) > 1e-9:
            raise ParameterError(
                "parameter 'task.control_period_s' must be a whole multiple of 'task.dt_s'"
            )
        for name, value in vals.items():
            if isinstance(value, float) and not math.isfinite(value):
                raise ParameterError(f"parameter '{name}' must be finite, got {value!r}")
        SlowdownParams.from_params(vals, "safety", "task.f_prewarn_n")  # start_n checked
        return cls(flat=vals)

    def slowdown_zone(self) -> SlowdownZone:
        """Eq. M6, the bridge's slowdown zone, from ``safety.slowdown.*`` and the prewarning."""
        params = SlowdownParams.from_params(self.flat, "safety", "task.f_prewarn_n")
        return params.zone(self.task.f_prewarn_n)


def load_sim_config(overrides: str | os.PathLike[str] | dict[str, Any] | None = None) -> SimConfig:
    """The shipped ``config/peel_sim_node.yaml``, optionally overridden by a parameter file
    (ROS 2 layout) or a flat dict of dotted names."""
    if isinstance(overrides, dict):
        values = load_node_params(NODE)
        values.update(overrides)
    else:
        values = load_node_params(NODE, overrides)
    return SimConfig.from_params(values)
