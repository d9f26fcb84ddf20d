"""The reality-gap plant: the simulator's engine with shifted parameters and extra physics, in
named severity levels (docs/simulator.md, "Plant severity levels").

A level is a cumulative set of physically motivated differences from the pretraining simulator
(``source="sim"``); every value lives in ``config/peel_sim_node.yaml`` (groups ``plant``,
``plant_l2``, ``plant_l3``) and ``plant.level`` selects the one ``source="plant"`` runs:

* **level 0** -- the simulator itself (its intervals, no effect, no lag, no drift);
* **level 1** -- the plant of docs/simulator.md revision 2 (group ``plant``): a stickier,
  softer, less viscous pad batch (shifted P_k intervals), residual vacuum near C
  (:class:`~peel_sim_node.effects.ResidualVacuum`), actuator lag, sensor drift;
* **level 2** -- level 1 plus (group ``plant_l2``) another pad batch and adhesive state: a foam
  of lower viscosity (damping interval) and a peel front whose resistance barely depends on
  the peel rate (polishing slurry left between glass and pad: ``rate_gain_scale``), with a
  firmer static hold (``base_load_scale``);
* **level 3** -- level 2 plus (group ``plant_l3``) a wet pad surface: the polishing slurry
  lubricates the blade-pad contact (lower sliding friction interval, static/kinetic ratio closer
  to 1, so weaker stick-slip), and a slower actuator (longer speed lag).

Level 1's sensor drift is measurement only (not part of the dynamics, so not in ``rollout``).
Extra effects are injected with ``PeelEnv(..., effects=[...])`` (see :mod:`.effects`).
"""

from __future__ import annotations

from dataclasses import dataclass

from peel_msgs_py.errors import PeelError

from .config import SimConfig
from .effects import Effect, ResidualVacuum

SOURCES: tuple[str, ...] = ("sim", "plant")
#: Plant severity levels, mildest first (0 = the simulator).
LEVELS: tuple[int, ...] = (0, 1, 2, 3)
LEVEL_NAMES: dict[int, str] = {
    0: "simulator",
    1: "plant rev. 2 (softer, less viscous pad; residual vacuum; lag; drift)",
    2: "level 1 + low-viscosity pad batch, rate-insensitive adhesive state",
    3: "level 2 + wet, slurry-lubricated pad surface, slower actuator",
}


@dataclass(frozen=True)
class PlantSpec:
    """Everything that makes one severity level differ from the simulator."""

    level: int
    friction: tuple[float, float]
    stiffness: tuple[float, float]  # N/m
    damping: tuple[float, float]  # N s/m
    residual_vacuum_n: float = 0.0
    residual_length_mm: float = 4.0
    actuator_lag_s: float = 0.0
    drift_n_per_sqrt_s: float = 0.0
    base_load_scale: float = 1.0  # x load.base_n
    rate_gain_scale: float = 1.0  # x load.rate_gain
    static_friction_ratio: float | None = None  # None: scene.static_friction_ratio

    @property
    def name(self) -> str:
        return LEVEL_NAMES[self.level]

    def effects(self) -> list[Effect]:
        """The level's declared state-dependent effects."""
        out: list[Effect] = []
        if self.residual_vacuum_n > 0.0:
            out.append(ResidualVacuum(self.residual_vacuum_n, self.residual_length_mm))
        return out


def check_level(level: int) -> int:
    """``level`` as an int, or PeelError naming the known levels."""
    if isinstance(level, bool) or not isinstance(level, int) or level not in LEVELS:
        raise PeelError(f"plant level must be one of {list(LEVELS)}, got {level!r}")
    return int(level)


def plant_spec(cfg: SimConfig, level: int | None = None) -> PlantSpec:
    """The differences of plant level ``level`` (default ``plant.level``) from the simulator."""
    lvl = check_level(cfg.plant.level if level is None else level)
    r = cfg.randomization
    if lvl == 0:
        return PlantSpec(0, (r.friction_low, r.friction_high), (r.stiffness_low, r.stiffness_high),
                         (r.damping_low, r.damping_high))
    p = cfg.plant
    spec = PlantSpec(1, (p.friction_low, p.friction_high), (p.stiffness_low, p.stiffness_high),
                     (p.damping_low, p.damping_high), p.residual_vacuum_n, p.residual_length_mm,
                     p.actuator_lag_s, p.drift_n_per_sqrt_s)
    if lvl == 1:
        return spec
    p2 = cfg.plant_l2
    spec = PlantSpec(2, (p2.friction_low, p2.friction_high),
                     (p2.stiffness_low, p2.stiffness_high), (p2.damping_low, p2.damping_high),
                     spec.residual_vacuum_n, spec.residual_length_mm, spec.actuator_lag_s,
                     spec.drift_n_per_sqrt_s, p2.base_load_scale, p2.rate_gain_scale)
    if lvl == 2:
        return spec
    p3 = cfg.plant_l3
    return PlantSpec(3, (p3.friction_low, p3.friction_high), spec.stiffness, spec.damping,
                     spec.residual_vacuum_n, spec.residual_length_mm, p3.actuator_lag_s,
                     spec.drift_n_per_sqrt_s, spec.base_load_scale * p3.base_load_scale,
                     spec.rate_gain_scale, p3.static_friction_ratio)


def source_spec(cfg: SimConfig, source: str, level: int | None = None) -> PlantSpec:
    """The spec a ``PeelEnv(source=...)`` runs: level 0 for the simulator, else the plant's."""
    if source not in SOURCES:
        raise PeelError(f"source must be one of {SOURCES}, got {source!r}")
    return plant_spec(cfg, 0) if source == "sim" else plant_spec(cfg, level)


def declared_effects(cfg: SimConfig, level: int | None = None) -> list[Effect]:
    """The plant's declared state-dependent effects at ``level`` (default ``plant.level``)."""
    return plant_spec(cfg, level).effects()


def actuator_lag_s(cfg: SimConfig, source: str, level: int | None = None) -> float:
    """Time constant of the robot's speed response (0 = none, the simulator)."""
    return source_spec(cfg, source, level).actuator_lag_s


def drift_rate(cfg: SimConfig, source: str, level: int | None = None) -> float:
    """Sensor drift rate, N/sqrt(s) (plant only)."""
    return source_spec(cfg, source, level).drift_n_per_sqrt_s


#: How the process changes over consecutive peels (docs/simulator.md, "Sequences").
SEQUENCES: tuple[str, ...] = ("stationary", "drift", "batch-switch")


def check_sequence(sequence: str) -> str:
    """``sequence`` if known, else PeelError naming the known ones."""
    if sequence not in SEQUENCES:
        raise PeelError(f"sequence must be one of {list(SEQUENCES)}, got {sequence!r}")
    return sequence


def sequence_params(cfg: SimConfig, params: dict[str, float], task: int,
                    sequence: str) -> dict[str, float]:
    """The physical parameters of consecutive peel ``task`` (1-based) of a ``sequence``, from
    the substrate's drawn P_k ``params`` (3.2.1):

    * ``stationary``: unchanged (every peel an independent draw of the same process);
    * ``drift``: pad wear -- the pad's friction rises by ``sequence.drift_friction_per_task``
      (relative) with every peel before this one: ``friction * (1 + r (task - 1))``;
    * ``batch-switch``: from task ``sequence.switch_task`` on a new pad batch, whose friction,
      stiffness and damping are the drawn ones times ``sequence.switch_*_scale``.
    """
    check_sequence(sequence)
    if task < 1:
        raise PeelError(f"task must be >= 1, got {task}")
    out = dict(params)
    sq = cfg.sequence
    if sequence == "drift":
        out["friction"] = params["friction"] * (1.0 + sq.drift_friction_per_task * (task - 1))
    elif sequence == "batch-switch" and task >= sq.switch_task:
        out["friction"] = params["friction"] * sq.switch_friction_scale
        out["stiffness"] = params["stiffness"] * sq.switch_stiffness_scale
        out["damping"] = params["damping"] * sq.switch_damping_scale
    return out
