"""Effects: physical behaviour the pretraining simulator lacks, injected into the plant.

An :class:`Effect` is any callable ``effect(state: EffectState) -> EffectAction | None``. The
environment calls every effect once per sample (0.1 s), before the engine steps of that sample,
with the state at the start of the sample; the returned action holds over the sample:

* ``load_n``: extra downward load (N) of the substrate on the blade. It goes through the engine:
  the blade-glass contact carries it, so it raises F_RZ and, through friction, F_RX.
* ``resist_n``: extra force (N) opposing the blade's forward motion (applied to the blade joint;
  the sensor sees it in F_RX and the blade slows down / sticks longer).
* ``v_scale`` / ``v_offset_mmps``: change of the robot's actual speed relative to the command
  (``u * v_scale + v_offset``), e.g. a slipping gripper or a miscalibrated axis.

Effects must be pure functions of the state (no hidden state), because :meth:`PeelEnv.rollout`
replays them from saved states: the oracle of the plant includes every effect. Pass them as
``PeelEnv(cfg, source="plant", effects=[...])``; the plant's declared effects
(:func:`peel_sim_node.plant.declared_effects`) are added automatically.

Example, a sticky patch between 10 and 12 mm::

    def sticky_patch(s: EffectState) -> EffectAction:
        return EffectAction(resist_n=4.0 if 10.0 <= s.q_mm < 12.0 else 0.0)

From the command line, ``peel graph --effect mymodule:sticky_patch`` (the simulator node's
parameter ``node.effects``) and ``peel experiment --effect ...`` add such a function to the
plant (:func:`load_effects`); a few ready-made ones are in :mod:`peel_sim_node.example_effects`
(docs/residual.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class EffectState:
    """State at the start of a sample: time (s), blade position (mm), blade speed (mm/s),
    command (mm/s), last true forces (N, without sensor noise) and the task's parameters."""

    t_s: float
    q_mm: float
    v_mmps: float
    u_mmps: float
    fx_n: float
    fz_n: float
    params: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class EffectAction:
    """What an effect does over one sample (see the module docstring)."""

    load_n: float = 0.0
    resist_n: float = 0.0
    v_scale: float = 1.0
    v_offset_mmps: float = 0.0


@runtime_checkable
class Effect(Protocol):
    """A callable changing forces or motion from the state (module docstring)."""

    def __call__(self, state: EffectState) -> EffectAction | None: ...


def combine(actions: list[EffectAction | None]) -> EffectAction:
    """Loads and resistances add, speed scales multiply, offsets add."""
    load = resist = off = 0.0
    scale = 1.0
    for a in actions:
        if a is None:
            continue
        if not isinstance(a, EffectAction):
            raise TypeError(f"an effect returned {type(a).__name__}, expected EffectAction")
        load += a.load_n
        resist += a.resist_n
        scale *= a.v_scale
        off += a.v_offset_mmps
    for name, val in (("load_n", load), ("resist_n", resist), ("v_scale", scale),
                      ("v_offset_mmps", off)):
        if not math.isfinite(val):
            raise ValueError(f"effect action field {name!r} is not finite")
    return EffectAction(load_n=load, resist_n=resist, v_scale=scale, v_offset_mmps=off)


@dataclass(frozen=True)
class ResidualVacuum:
    """Declared plant effect: vacuum left under the glass near C that the simulator lacks.

    Extra hold-down load ``load_n * exp(-q / length_mm)`` (N) on the blade."""

    load_n: float
    length_mm: float

    def __call__(self, state: EffectState) -> EffectAction:
        return EffectAction(load_n=self.load_n * math.exp(-max(state.q_mm, 0.0) / self.length_mm))


def load_effect(spec: str) -> Effect:
    """The user effect named ``module:function`` (an importable module and a callable in it,
    ``function(EffectState) -> EffectAction | None``), for ``peel graph --effect``.

    This imports the named module: the user's own code, named on the command line or in the
    simulator node's parameters, never read from a data file. Anything that goes wrong (bad
    form, a module that does not import or raises while importing, no such callable) is a
    :class:`~peel_msgs_py.errors.PeelError` in one line naming the effect.
    """
    import importlib

    from peel_msgs_py.errors import PeelError

    module, sep, name = str(spec).strip().partition(":")
    if not sep or not module or not name:
        raise PeelError(f"effect {spec!r} must be given as module:function")
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # the user's module: any failure to import it is bad input
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PeelError(f"effect {spec!r}: cannot import {module!r} ({first})") from None
    func: object = mod
    for part in name.split("."):
        func = getattr(func, part, None)
        if func is None:
            raise PeelError(f"effect {spec!r}: {module!r} has no {name!r}")
    if not callable(func):
        raise PeelError(f"effect {spec!r}: {name!r} is not callable")
    return func  # type: ignore[return-value]


def load_effects(specs: Sequence[str]) -> list[Effect]:
    """:func:`load_effect` for each non-empty spec (a repeated one adds twice); ``[""]`` (the
    default of ``node.effects``) and ``[]`` are none."""
    return [load_effect(s) for s in specs if str(s).strip()]
