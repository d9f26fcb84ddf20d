"""Plant safety (docs/simulator.md): careful peeling never reaches the 20 N prewarning at any
plant severity level, as in the simulator; fast peeling does in the simulator and at level 1
(levels 2-3 have forces that barely rise with speed: that is their reality gap)."""

import numpy as np
import pytest

from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv, sample_params
from peel_sim_node.episode import run_episode
from peel_sim_node.plant import plant_spec

CFG = load_sim_config()
F_PRE = CFG.task.f_prewarn_n


def peak(tr):
    return float(np.max(np.maximum(np.abs(tr.fx), np.abs(tr.fz))))


def constant(u):
    return lambda hist: u


def worst_corner(level):
    """Every parameter at the top of its interval and every pad tile at the strongest
    adhesion: the largest breakaway force the level can draw (level 0 = the simulator)."""
    spec = plant_spec(CFG, level)
    p = {"friction": spec.friction[1], "stiffness": spec.stiffness[1], "damping": spec.damping[1]}
    p.update({f"tile_{i}": 1.0 + CFG.randomization.tile_spread for i in range(CFG.scene.n_tiles)})
    return p


@pytest.mark.parametrize("source,level", [("sim", 0), ("plant", 1), ("plant", 2), ("plant", 3)])
def test_careful_peeling_of_the_worst_corner_stays_below_prewarning(source, level):
    with PeelEnv(CFG, source=source, level=level, seed=4) as env:
        for u, seed in ((0.5, 4), (1.0, 5)):
            tr = run_episode(env, constant(u), seed=seed, params=worst_corner(level))
            assert tr.outcome == "done", (source, level, u, tr.outcome)
            assert peak(tr) < F_PRE - 0.4, (source, level, u, peak(tr))


@pytest.mark.parametrize("level", [1, 2, 3])
def test_plant_draws_careful_safe(level):
    rng = np.random.default_rng(3)
    sets = [sample_params(CFG, rng, "plant", level) for _ in range(5)]
    with PeelEnv(CFG, source="plant", level=level, seed=0) as env:
        careful = [run_episode(env, constant(1.0), seed=10 + i, params=p)
                   for i, p in enumerate(sets)]
    assert [t.outcome for t in careful] == ["done"] * 5
    assert max(peak(t) for t in careful) < F_PRE


def test_level1_fast_peeling_stops():
    # the planner's top speed (8 mm/s) stops substrates of level 1 (4 of 8 draws of seed 3)
    rng = np.random.default_rng(3)
    sets = [sample_params(CFG, rng, "plant", 1) for _ in range(8)]
    with PeelEnv(CFG, source="plant", level=1, seed=0) as env:
        fast = [run_episode(env, constant(8.0), seed=20 + i, params=p)
                for i, p in enumerate(sets)]
    stopped = [t for t in fast if t.outcome == "safety_stop"]
    assert len(stopped) >= 3, [t.outcome for t in fast]
    assert all(t.q[-1] < CFG.task.q_ter_mm for t in stopped)
