"""The reality-gap plant: the simulator's engine with shifted parameters and extra physics.

Compared with the pretraining simulator (``source="sim"``) the plant (``source="plant"``)

1. draws P_k from the shifted intervals ``plant.*_low/high`` (a stickier, softer, more
   viscous pad: forces rise faster with speed; bounded so careful peeling stays below 20 N);
2. has *residual vacuum* near C (:class:`~peel_sim_node.effects.ResidualVacuum`): an extra
   hold-down load decaying with q, so the start is harder than the simulator predicts;
3. has *actuator lag*: the robot's speed follows the command with a first-order lag
   (``plant.actuator_lag_s``) instead of jumping to it;
4. has *sensor drift*: a slow random walk on both force channels (``plant.drift_n_per_sqrt_s``),
   measurement only (not part of the dynamics, so not in ``rollout``).

Extra effects are injected with ``PeelEnv(..., effects=[...])`` (see :mod:`.effects`).
"""

from __future__ import annotations

from .config import SimConfig
from .effects import Effect, ResidualVacuum

SOURCES: tuple[str, ...] = ("sim", "plant")


def declared_effects(cfg: SimConfig) -> list[Effect]:
    """The plant's declared state-dependent effects (residual vacuum)."""
    if cfg.plant.residual_vacuum_n > 0.0:
        return [ResidualVacuum(cfg.plant.residual_vacuum_n, cfg.plant.residual_length_mm)]
    return []


def actuator_lag_s(cfg: SimConfig, source: str) -> float:
    """Time constant of the robot's speed response (0 = none, the simulator)."""
    return cfg.plant.actuator_lag_s if source == "plant" else 0.0


def drift_rate(cfg: SimConfig, source: str) -> float:
    """Sensor drift rate, N/sqrt(s) (plant only)."""
    return cfg.plant.drift_n_per_sqrt_s if source == "plant" else 0.0
