"""Planner parameters: cost critics (Eq. 3-5), MPPI (Algorithm 2, Eq. 28-38), dynamics, safety.

The values live in ``config/peel_planner_node.yaml`` (section ``peel_planner_node:``), each
commented with its equation and unit. :class:`PlannerConfig` is the validated, typed view of the
flat parameter dict that ROS 2 would hand to the node. Every section is a frozen dataclass; a
field is read from the parameter ``<prefix>.<field>`` of its section (a nested dataclass field
is a sub-section, ``cost.barrier.weight``), else from the shared ``task.`` or ``safety.`` one
(``cost.dt_s`` <- ``task.dt_s``): one rule, :func:`_param_name`.

Sections:

* ``cost.<critic>.*``: one prefix per cost term (docs/planner.md, "Cost critics"): the paper's
  ``progress``, ``force_x``, ``force_z`` (Eq. 4) and ``terminal`` (phi, Eq. 5), and the
  planning-only ``barrier`` and ``cost_to_go``;
* ``mppi.*``: sampling, temperature, Sigma estimation, speed limits, Eq. 38's control term;
* ``dynamics.*``: which implementation rolls the model out (``fused`` or ``reference``) and the
  fused one's own settings (``dynamics.fused.workers``, ``chunk_samples``, ``dtype``,
  ``native_loop``): speed only, never the algorithm;
* ``safety.*``: the end-of-task conditions (section 4.2) and the guard of the force limit
  under model error (``safety.margin.*``, ``safety.null_sample``, ``safety.check.*``,
  ``safety.fallback``, ``safety.slowdown.*``; docs/planner.md, Eq. M1-M5).

Time base (docs/CONTRACT.md, section 4.2): the forward model steps ``dt_s`` = 0.1 s; one MPPI
horizon step holds the sampled velocity ``v_t = u_t + eps_t`` for ``steps_per_horizon_step``
model steps, which by default is one control period (0.5 s = 5 x 0.1 s). A plan therefore looks
``horizon * steps_per_horizon_step * dt_s`` seconds ahead (2.5 s by default).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import asdict, dataclass, fields
from typing import Any

from peel_msgs_py.errors import ParameterError
from peel_msgs_py.params import ParamSpec, load_node_params, validate

NODE_NAME = "peel_planner_node"

#: Every parameter the planner library reads, with its range and paper reference.
PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("task.q0_mm", float, 0.0, "start position q_0, mm (Eq. 4)"),
    ParamSpec("task.q_ter_mm", float, 25.0, "end position q_ter, mm (Eq. 4-5)", min=1e-3),
    ParamSpec("task.t_max_s", float, 60.0, "upper bound time t_max, s (Eq. 5)", min=1e-3),
    ParamSpec("task.dt_s", float, 0.1, "model step / sampling period, s (4.2)", min=1e-4),
    ParamSpec("task.control_period_s", float, 0.5, "control period, s (4.2)", min=1e-4),
    ParamSpec("cost.progress.weight", float, 1.0, "progress weight w_dis (Eq. 4)", min=0.0),
    ParamSpec("cost.force_x.weight", float, 0.25, "horizontal force weight w_fX (Eq. 4)",
              min=0.0),
    ParamSpec("cost.force_x.f_lim_n", float, 20.0, "F_lim^RX, N (Eq. 4)", min=1e-6),
    ParamSpec("cost.force_z.weight", float, 0.25, "vertical force weight w_fZ (Eq. 4)", min=0.0),
    ParamSpec("cost.force_z.f_lim_n", float, 20.0, "F_lim^RZ, N (Eq. 4)", min=1e-6),
    ParamSpec("cost.terminal.weight", float, 1.0, "factor on phi (Eq. 5; paper: 1)", min=0.0),
    ParamSpec("cost.terminal.phi_late", float, 1.0, "phi, reached after t_max (Eq. 5)", min=0.0),
    ParamSpec("cost.terminal.phi_fail", float, 2.0, "phi, not reached by t_max (Eq. 5)",
              min=0.0),
    ParamSpec("cost.cost_to_go.weight", float, 14.0,
              "planning only: cost per (q_ter - q_0) still to go at the horizon end", min=0.0),
    ParamSpec("cost.barrier.weight", float, 8.0, "planning only: barrier weight", min=0.0),
    ParamSpec("cost.barrier.start_n", float, 15.0, "planning only: barrier onset |F|, N",
              min=0.0),
    ParamSpec("cost.barrier.stop_weight", float, 10.0,
              "planning only: cost per sample of a predicted prewarning", min=0.0),
    ParamSpec("cost.barrier.margin_ramp", bool, True,
              "planning only: the margin m_a of Eq. M1 also ends the quadratic ramp at "
              "f_prewarn_n - m_a (Eq. M2); false: it moves only the stop term"),
    ParamSpec("mppi.n_samples", int, 50, "N sampled sequences (Alg. 2)", min=1, max=1_000_000),
    ParamSpec("mppi.horizon", int, 5, "H horizon steps (Alg. 2)", min=1, max=1000),
    ParamSpec("mppi.lambda", float, 0.1, "temperature lambda (Eq. 38)", min=1e-9),
    ParamSpec("mppi.steps_per_horizon_step", int, 5, "model steps per horizon step", min=1,
              max=1000),
    ParamSpec("mppi.sigma0", float, 1.0, "initial Sigma, (mm/s)^2 (Eq. 2)", min=1e-12),
    ParamSpec("mppi.sigma_min", float, 0.5, "Sigma floor, (mm/s)^2 (Alg. 2 l.17)", min=1e-12),
    ParamSpec("mppi.sigma_max", float, 4.0, "Sigma ceiling, (mm/s)^2 (Alg. 2 l.17)", min=1e-12),
    ParamSpec("mppi.sigma_window", int, 10, "errors kept in D_Sigma (Alg. 2 l.15)", min=1,
              max=100_000),
    ParamSpec("mppi.sigma_min_count", int, 3, "errors before Sigma is re-estimated", min=1,
              max=100_000),
    ParamSpec("mppi.u_min", float, 0.5, "lowest speed command, mm/s"),
    ParamSpec("mppi.u_max", float, 8.0, "highest speed command, mm/s"),
    ParamSpec("mppi.u_init", float, 1.0, "initial U / shift fill, mm/s"),
    ParamSpec("mppi.shift_fill", str, "last", "shift fill (Alg. 2 l.18-19)",
              choices=("last", "init")),
    ParamSpec("mppi.control_cost_scale", float, 0.1, "factor on Eq. 38's control term", min=0.0),
    ParamSpec("mppi.control_cost_sigma", str, "sigma0",
              "Sigma in Eq. 38's control term: the re-estimated Sigma or sigma0",
              choices=("estimate", "sigma0")),
    ParamSpec("mppi.control_term", str, "per_step",
              "Eq. 38's likelihood ratio: per-step Sigma^-1 (Eq. 36-37) or the joint AR(1) "
              "precision of the horizon", choices=("per_step", "joint")),
    ParamSpec("mppi.noise_correlation", float, 0.8,
              "rho of eps_t = rho eps_(t-1) + sqrt(1 - rho^2) z_t over the horizon", min=0.0,
              max=0.99),
    ParamSpec("mppi.iterations", int, 1, "MPPI updates per plan()", min=1, max=1000),
    ParamSpec("mppi.seed", int, 0, "noise seed", min=0),
    ParamSpec("mppi.dtype", str, "float32", "torch dtype of the noise, costs and weights",
              choices=("float32", "float64")),
    ParamSpec("dynamics.implementation", str, "fused",
              "fused (when the model supports it) or reference (the model stepped as defined)",
              choices=("fused", "reference")),
    ParamSpec("dynamics.fused.workers", int, 2, "threads rolling out sample chunks", min=1,
              max=64),
    ParamSpec("dynamics.fused.chunk_samples", int, 256,
              "samples per chunk: chunks are cut by N and this size only", min=1,
              max=1_000_000),
    ParamSpec("dynamics.fused.dtype", str, "float32", "torch dtype of the fused rollout",
              choices=("float32", "float64")),
    ParamSpec("dynamics.fused.native_loop", bool, True,
              "run the model-step loop in C++ when it is built"),
    ParamSpec("safety.f_prewarn_n", float, 20.0, "safety prewarning on |F|, N (4.2)", min=1e-6),
    ParamSpec("safety.margin.enabled", bool, True,
              "tighten the force limit by the measured model error (Eq. M1-M2); false: m_a = 0"),
    ParamSpec("safety.margin.delta", float, 0.2,
              "delta of Eq. M1: m_a = the conformal (1 - delta) upper quantile of e = measured - "
              "predicted |F_a| of the issued command, so P(e > m_a) <= delta (Eq. M2)",
              min=0.001, max=0.999),
    ParamSpec("safety.margin.window", int, 20,
              "model steps of force error per axis in the margin's window (Eq. M1)", min=1,
              max=100_000),
    ParamSpec("safety.margin.min_count", int, 10,
              "errors per axis before Eq. M1 replaces safety.margin.init_n", min=1,
              max=100_000),
    ParamSpec("safety.margin.init_n", float, 0.5,
              "margin before min_count errors exist (each task starts with it), N", min=0.0,
              max=20.0),
    ParamSpec("safety.margin.max_n", float, 6.0, "ceiling m_max of the margin, N (Eq. M1)",
              min=0.0, max=20.0),
    ParamSpec("safety.margin.carry_over", bool, False,
              "a new task starts with the previous task's Eq. M1 error window (Eq. M8) instead "
              "of an empty one and init_n"),
    ParamSpec("safety.margin.lead_enabled", bool, False,
              "also measure the model's error over a whole horizon (Eq. M7): m_a = max(Eq. M1's "
              "margin, the conformal quantile of the horizon errors)"),
    ParamSpec("safety.margin.lead_window", int, 50,
              "horizon errors per axis in Eq. M7's window (one replay adds H * k of them)",
              min=1, max=100_000),
    ParamSpec("safety.null_sample", bool, True,
              "add the slowest sequence (u_min over the horizon) to the N samples (Eq. 31)"),
    ParamSpec("safety.check.enabled", bool, True,
              "check the command against the model before it goes out (Eq. M3)"),
    ParamSpec("safety.check.candidates", int, 8,
              "speeds u_min..max v_0 rolled out with the samples for the check (Eq. M3)",
              min=2, max=1000),
    ParamSpec("safety.fallback", str, "least_force",
              "command when even u_min is predicted over the tightened limit (Eq. M4): the "
              "candidate of least predicted force, or u_min; both keep the blade moving",
              choices=("least_force", "u_min")),
    ParamSpec("safety.slowdown.enabled", bool, False,
              "scale the command down by the measured force peak of the last control period "
              "(Eq. M5); false: the measured force does not limit the command"),
    ParamSpec("safety.slowdown.start_n", float, 17.0,
              "measured peak max_a |F_a| from which Eq. M5 scales the command, N; below "
              "safety.f_prewarn_n", min=0.0, max=100.0),
)


# ---------------------------------------------------------------- cost critics (cost.py)
@dataclass(frozen=True)
class ProgressConfig:
    """Eq. 4's progress term: ``-weight (q_t - q_{t-1}) / (q_ter - q_0)``, weight = w_dis."""

    weight: float = 1.0


@dataclass(frozen=True)
class ForceConfig:
    """One force term of Eq. 4: ``weight |F_t| / f_lim_n`` (w_fX / F_lim^RX or w_fZ / F_lim^RZ)."""

    weight: float = 0.25
    f_lim_n: float = 20.0


@dataclass(frozen=True)
class TerminalConfig:
    """phi of Eq. 5: 0 / ``phi_late`` / ``phi_fail``, times ``weight`` (1 in the paper)."""

    weight: float = 1.0
    phi_late: float = 1.0
    phi_fail: float = 2.0


@dataclass(frozen=True)
class BarrierConfig:
    """Planning only: a barrier below the safety prewarning ``f_prewarn_n`` (docs/planner.md)."""

    weight: float = 8.0
    start_n: float = 15.0
    stop_weight: float = 10.0
    margin_ramp: bool = True
    f_prewarn_n: float = 20.0


@dataclass(frozen=True)
class CostToGoConfig:
    """Planning only: ``weight (q_ter - q_H) / (q_ter - q_0)`` at the horizon end."""

    weight: float = 14.0


@dataclass(frozen=True)
class CostConfig:
    """The task geometry (``task.*``) and one sub-section per cost critic (``cost.<name>.*``)."""

    q0_mm: float = 0.0
    q_ter_mm: float = 25.0
    t_max_s: float = 60.0
    dt_s: float = 0.1
    progress: ProgressConfig = ProgressConfig()
    force_x: ForceConfig = ForceConfig()
    force_z: ForceConfig = ForceConfig()
    terminal: TerminalConfig = TerminalConfig()
    barrier: BarrierConfig = BarrierConfig()
    cost_to_go: CostToGoConfig = CostToGoConfig()


# ---------------------------------------------------------------- MPPI (mppi.py)
@dataclass(frozen=True)
class MppiConfig:
    """Sampling, temperature, Sigma estimation, Eq. 38's control term and speed limits."""

    n_samples: int = 50
    horizon: int = 5
    lam: float = 0.1
    steps_per_horizon_step: int = 5
    sigma0: float = 1.0
    sigma_min: float = 0.5
    sigma_max: float = 4.0
    sigma_window: int = 10
    sigma_min_count: int = 3
    u_min: float = 0.5
    u_max: float = 8.0
    u_init: float = 1.0
    shift_fill: str = "last"
    control_cost_scale: float = 0.1
    control_cost_sigma: str = "sigma0"
    control_term: str = "per_step"
    noise_correlation: float = 0.8
    iterations: int = 1
    seed: int = 0
    dtype: str = "float32"
    dt_s: float = 0.1


# ---------------------------------------------------------------- dynamics (dynamics.py)
@dataclass(frozen=True)
class FusedConfig:
    """The fused dynamics' own settings (speed only; results depend on ``chunk_samples`` and
    ``dtype`` at float rounding, never on ``workers`` or ``native_loop``)."""

    workers: int = 2
    chunk_samples: int = 256
    dtype: str = "float32"
    native_loop: bool = True


@dataclass(frozen=True)
class DynamicsConfig:
    """Which implementation rolls the forward model out, and the fused one's settings."""

    implementation: str = "fused"
    dt_s: float = 0.1
    fused: FusedConfig = FusedConfig()


#: The guard of the force limit (Eq. M1-M5) switched off (the planner without it) and on with
#: the shipped values (config/peel_planner_node.yaml), as ``PlannerConfig.replace`` overrides.
UNGUARDED: dict[str, Any] = {"safety.margin.enabled": False, "safety.margin.init_n": 0.0,
                             "safety.null_sample": False, "safety.check.enabled": False,
                             "safety.slowdown.enabled": False}
GUARDED: dict[str, Any] = {"safety.margin.enabled": True, "safety.margin.delta": 0.2,
                           "safety.margin.init_n": 0.5, "safety.null_sample": True,
                           "safety.check.enabled": True, "safety.fallback": "least_force"}


@dataclass(frozen=True)
class MarginConfig:
    """The force margin from the model's measured error (docs/planner.md, Eq. M1)."""

    enabled: bool = True
    delta: float = 0.2
    window: int = 20
    min_count: int = 10
    init_n: float = 0.5
    max_n: float = 6.0
    lead_enabled: bool = False
    lead_window: int = 50
    carry_over: bool = False


@dataclass(frozen=True)
class CheckConfig:
    """The check of the command against the model before it goes out (Eq. M3)."""

    enabled: bool = True
    candidates: int = 8


@dataclass(frozen=True)
class SlowdownConfig:
    """The command scaled down by the measured force peak (docs/planner.md, Eq. M5)."""

    enabled: bool = False
    start_n: float = 17.0


@dataclass(frozen=True)
class SafetyConfig:
    """End-of-task conditions (section 4.2) and the guard of the force limit (Eq. M1-M5)."""

    f_prewarn_n: float = 20.0
    t_max_s: float = 60.0
    q_ter_mm: float = 25.0
    margin: MarginConfig = MarginConfig()
    check: CheckConfig = CheckConfig()
    slowdown: SlowdownConfig = SlowdownConfig()
    null_sample: bool = True
    fallback: str = "least_force"


@dataclass(frozen=True)
class PlannerConfig:
    """The planner's whole configuration; build it with :meth:`from_params`."""

    cost: CostConfig = CostConfig()
    mppi: MppiConfig = MppiConfig()
    dynamics: DynamicsConfig = DynamicsConfig()
    safety: SafetyConfig = SafetyConfig()
    control_period_s: float = 0.5

    @classmethod
    def from_params(cls, flat: dict[str, Any], *, allow_unknown: bool = True) -> PlannerConfig:
        """Validate a flat (dotted-name) parameter dict; unknown names are ignored by default
        because the node's parameter set also holds non-library names (``model.path``...)."""
        p = validate(PARAM_SPECS, flat, allow_unknown=allow_unknown)
        _check_relations(p)
        sections = {name: _build(section, name, p) for name, section in _SECTIONS}
        return cls(**sections, control_period_s=p["task.control_period_s"])

    def to_params(self) -> dict[str, Any]:
        """The flat parameter dict this config was built from (inverse of :meth:`from_params`)."""
        flat = {"task.control_period_s": self.control_period_s}
        for name, _ in _SECTIONS:
            flat.update(_flatten(getattr(self, name), name))
        return flat

    def replace(self, **flat: Any) -> PlannerConfig:
        """A copy with some flat parameters changed, e.g. ``cfg.replace(**{"mppi.horizon": 10})``."""
        params = self.to_params()
        params.update(flat)
        return PlannerConfig.from_params(params, allow_unknown=False)

    def as_dict(self) -> dict[str, Any]:
        """Nested plain dict (for JSON reports)."""
        return {f.name: (asdict(getattr(self, f.name)) if f.name != "control_period_s"
                         else self.control_period_s) for f in fields(self)}


def _check_relations(p: dict[str, Any]) -> None:
    """Constraints between parameters, each named in its error."""
    if p["mppi.u_min"] > p["mppi.u_max"]:
        raise ParameterError("parameter 'mppi.u_min' must not exceed 'mppi.u_max'")
    if p["mppi.sigma_min"] > p["mppi.sigma_max"]:
        raise ParameterError("parameter 'mppi.sigma_min' must not exceed 'mppi.sigma_max'")
    if p["task.q_ter_mm"] <= p["task.q0_mm"]:
        raise ParameterError("parameter 'task.q_ter_mm' must exceed 'task.q0_mm'")
    if p["safety.slowdown.start_n"] >= p["safety.f_prewarn_n"]:
        raise ParameterError("parameter 'safety.slowdown.start_n' must be below "
                             "'safety.f_prewarn_n'")
    if p["cost.barrier.start_n"] >= p["safety.f_prewarn_n"]:
        raise ParameterError("parameter 'cost.barrier.start_n' must be below "
                             "'safety.f_prewarn_n'")
    period = p["task.dt_s"] * p["mppi.steps_per_horizon_step"]
    if abs(period - p["task.control_period_s"]) > 1e-9 * max(1.0, period):
        raise ParameterError(
            f"parameter 'task.control_period_s' = {p['task.control_period_s']} must equal "
            f"task.dt_s * mppi.steps_per_horizon_step = {period:g}"
        )


#: the config sections and the dataclass of each
_SECTIONS: tuple[tuple[str, type], ...] = (
    ("cost", CostConfig), ("mppi", MppiConfig), ("dynamics", DynamicsConfig),
    ("safety", SafetyConfig))
_SPEC_NAMES = frozenset(spec.name for spec in PARAM_SPECS)


def _param_name(prefix: str, field: str) -> str:
    """The parameter behind a section field: ``<prefix>.<field>``, else the shared ``task.`` /
    ``safety.`` one (e.g. cost.dt_s <- task.dt_s); ``mppi.lam`` is ``mppi.lambda``."""
    if (prefix, field) == ("mppi", "lam"):
        return "mppi.lambda"
    for candidate in (prefix, "task", "safety"):
        if f"{candidate}.{field}" in _SPEC_NAMES:
            return f"{candidate}.{field}"
    raise AssertionError(f"no parameter for {prefix}.{field}")  # a field without a ParamSpec


def _build(section: type, prefix: str, p: dict[str, Any]) -> Any:
    """The dataclass ``section`` filled from the validated flat dict (nested ones recursively)."""
    values = {}
    for f in fields(section):
        sub = f.default if dataclasses.is_dataclass(f.default) else None
        values[f.name] = (_build(type(sub), f"{prefix}.{f.name}", p) if sub is not None
                          else p[_param_name(prefix, f.name)])
    return section(**values)


def _flatten(part: Any, prefix: str) -> dict[str, Any]:
    """Inverse of :func:`_build`: the flat parameters of one section."""
    flat: dict[str, Any] = {}
    for f in fields(part):
        value = getattr(part, f.name)
        if dataclasses.is_dataclass(value):
            flat.update(_flatten(value, f"{prefix}.{f.name}"))
        else:
            flat[_param_name(prefix, f.name)] = value
    return flat


def load_planner_config(overrides: str | os.PathLike[str] | None = None) -> PlannerConfig:
    """The shipped ``config/peel_planner_node.yaml``, with an optional override file on top."""
    return PlannerConfig.from_params(load_node_params(NODE_NAME, overrides))
