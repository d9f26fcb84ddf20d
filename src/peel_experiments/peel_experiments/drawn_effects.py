"""Effects drawn as the residual power study draws them, acting on the plant while it peels.

The power study (:mod:`peel_residual.study`, docs/residual.md) adds its drawn effects to forces
already recorded. The end-to-end loop (bag -> named effect -> corrected model -> planner cost
before and after) needs the effect in the plant, where the planner feels it: :class:`PlantEffect`
turns one draw of :func:`peel_residual.inject.draw` (family, channel, signed amplitude A, shape
parameters) into an :class:`~peel_sim_node.effects.Effect` with g = A s(x) of the study's shape
(:func:`peel_residual.inject.shape_of`) evaluated on the sample's state:

* on F_RZ an extra hold-down load g (``load_n``): the contact carries it, so the sensor sees it
  in F_RZ and, through friction, in F_RX;
* on F_RX an extra resistance g to the blade's forward motion (``resist_n``).

The families drawn (:data:`PLANT_FAMILIES`) are the study's force families whose shape is a
function of the sample's state alone, as an effect must be: every one but ``hysteresis`` (the
previous sample's speed), ``cross_talk`` (a force that feeds back on the force) and
``task_offset`` (the task's place in the sequence). Draw ``i`` of seed ``S`` uses
``numpy.random.default_rng([S, i])``: the family uniformly from :data:`PLANT_FAMILIES`, the
amplitude uniformly from :data:`AMPLITUDES_N`, then sign, channel and shape as the study draws
them.

    python -m peel_experiments.drawn_effects --seed S [--count K] --out DIR [--force]

writes, for each draw, ``DIR/drawn_effect_<i>.py``, a module whose ``effect`` is that draw
(``peel graph --effect drawn_effect_<i>:effect`` with ``DIR`` on ``PYTHONPATH``), and
``DIR/draws.json`` with every draw; prints the JSON. Used by ``scripts/residual_demo.sh``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.cliargs import ArgumentParser, nonnegative_int, positive_int, run_main
from peel_msgs_py.errors import PeelError
from peel_residual.inject import SHAPE_RANGES, Injection, draw, shape_of
from peel_sim_node.effects import EffectAction, EffectState

#: The study's force families an effect of the plant can carry (module docstring).
PLANT_FAMILIES: tuple[str, ...] = tuple(f for f in SHAPE_RANGES
                                       if f not in ("hysteresis", "cross_talk"))
#: Amplitudes drawn (N): the study's targets hold at 1 N and above.
AMPLITUDES_N: tuple[float, ...] = (1.0, 2.0)


@dataclass(frozen=True)
class PlantEffect:
    """One drawn effect acting on the plant (module docstring): g = A s(x) as a load on F_RZ
    or a resistance on F_RX."""

    family: str
    channel: str
    amplitude_n: float
    shape: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.family not in PLANT_FAMILIES:
            raise ValueError(f"family {self.family!r} cannot act on the plant "
                             f"(these can: {', '.join(PLANT_FAMILIES)})")
        if self.channel not in ("fx", "fz"):
            raise ValueError(f"channel {self.channel!r} is not fx or fz")

    def __call__(self, s: EffectState) -> EffectAction:
        g = self.amplitude_n * float(shape_of(self.family, self.shape, v=np.array([s.v_mmps]),
                                              q=np.array([s.q_mm]), t=np.array([s.t_s]))[0])
        return EffectAction(load_n=g) if self.channel == "fz" else EffectAction(resist_n=g)

    def to_json(self) -> dict[str, Any]:
        return Injection(self.family, self.channel, self.amplitude_n, dict(self.shape)).to_json()


def draw_plant_effect(seed: int, index: int) -> PlantEffect:
    """Draw ``index`` of ``seed`` (module docstring)."""
    rng = np.random.default_rng([seed, index])
    family = PLANT_FAMILIES[int(rng.integers(len(PLANT_FAMILIES)))]
    amp = AMPLITUDES_N[int(rng.integers(len(AMPLITUDES_N)))]
    inj = draw(family, amp, rng)
    return PlantEffect(inj.family, inj.channel, inj.amplitude_n, dict(inj.shape))


def module_text(e: PlantEffect, seed: int, index: int) -> str:
    """A module whose ``effect`` is ``e``, for ``peel graph --effect MODULE:effect``."""
    return (f'"""Draw {index} of seed {seed}: python -m peel_experiments.drawn_effects '
            f'--seed {seed}."""\n\n'
            "from peel_experiments.drawn_effects import PlantEffect\n\n"
            f"effect = PlantEffect(family={e.family!r}, channel={e.channel!r}, "
            f"amplitude_n={e.amplitude_n!r},\n                     shape={e.shape!r})\n")


def write_draws(seed: int, count: int, out: Path, force: bool = False) -> list[dict[str, Any]]:
    """Write the draws' modules and ``draws.json`` into ``out`` (module docstring)."""
    out.mkdir(parents=True, exist_ok=True)
    draws = []
    for i in range(count):
        path = out / f"drawn_effect_{i}.py"
        if path.exists() and not force:
            raise PeelError(f"{path} exists (give --force to replace it)")
        e = draw_plant_effect(seed, i)
        atomic_write_text(path, module_text(e, seed, i))
        draws.append({"index": i, "seed": seed, "module": path.stem, **e.to_json()})
    atomic_write_text(out / "draws.json", json.dumps(draws, indent=2) + "\n")
    return draws


def main(argv: Sequence[str] | None = None) -> int:
    p: argparse.ArgumentParser = ArgumentParser(prog="python -m peel_experiments.drawn_effects",
                                                description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=nonnegative_int, required=True, help="seed of the draws")
    p.add_argument("--count", type=positive_int, default=2, help="number of draws (2)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the modules")
    p.add_argument("--force", action="store_true", help="replace modules already there")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    print(json.dumps(write_draws(args.seed, args.count, args.out, args.force), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("drawn_effects", main))
