"""Ready-made undeclared effects for ``--effect`` (docs/residual.md): physics the simulator lacks.

Each is an :class:`~peel_sim_node.effects.Effect`, a pure function of the state; pass one as
``peel graph --plant plant --effect peel_sim_node.example_effects:vacuum_leak``. They are what
the residual analysis is demonstrated and tested on; nothing else in peel uses them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .effects import EffectAction, EffectState


def vacuum_leak(s: EffectState) -> EffectAction:
    """The hold-down load grows during the task, 0.3 N/s (a leak filling the pad's vacuum)."""
    return EffectAction(load_n=0.3 * s.t_s)


def slipping_axis(s: EffectState) -> EffectAction:
    """The robot moves at 75 % of the commanded speed (a slipping gripper, a miscalibrated axis)."""
    return EffectAction(v_scale=0.75)


def hose_drag(s: EffectState) -> EffectAction:
    """A hose dragged along by the carriage: 0.8 N per mm/s of the robot's (commanded) speed."""
    return EffectAction(resist_n=0.8 * s.u_mmps)


def grooved_pad(s: EffectState) -> EffectAction:
    """Extra hold-down from pad grooves 8 mm apart: 2 (1 + sin(2 pi q / 8 mm)) N."""
    return EffectAction(load_n=2.0 * (1.0 + math.sin(2.0 * math.pi * s.q_mm / 8.0)))


@dataclass(frozen=True)
class SpeedError:
    """The robot moves at ``u * scale + offset_mmps``: an axis calibration error or a slip
    (``scale``) and a constant speed error (``offset_mmps``, mm/s). A frozen value, so a drawn
    one pickles to worker processes and keys a cache (the residual power study's speed draws)."""

    scale: float = 1.0
    offset_mmps: float = 0.0

    def __call__(self, s: EffectState) -> EffectAction:
        return EffectAction(v_scale=self.scale, v_offset_mmps=self.offset_mmps)
