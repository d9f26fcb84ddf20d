"""Plant safety (issue 3 §1, §5): careful peeling never reaches the 20 N prewarning, fast
peeling does, in the plant as in the simulator."""

import numpy as np
import pytest

from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv, sample_params
from peel_sim_node.episode import run_episode

CFG = load_sim_config()
F_PRE = CFG.task.f_prewarn_n


def peak(tr):
    return float(np.max(np.maximum(np.abs(tr.fx), np.abs(tr.fz))))


def constant(u):
    return lambda hist: u


def worst_corner(source):
    """Every parameter at the top of its interval and every pad tile at the strongest
    adhesion: the largest breakaway force the source can draw."""
    grp = CFG.randomization if source == "sim" else CFG.plant
    p = {"friction": grp.friction_high, "stiffness": grp.stiffness_high,
         "damping": grp.damping_high}
    p.update({f"tile_{i}": 1.0 + CFG.randomization.tile_spread for i in range(CFG.scene.n_tiles)})
    return p


@pytest.mark.parametrize("source", ["sim", "plant"])
def test_careful_peeling_of_the_worst_corner_stays_below_prewarning(source):
    with PeelEnv(CFG, source=source, seed=4) as env:
        for u, seed in ((0.5, 4), (1.0, 5)):
            tr = run_episode(env, constant(u), seed=seed, params=worst_corner(source))
            assert tr.outcome == "done", (source, u, tr.outcome)
            assert peak(tr) < F_PRE - 0.5, (source, u, peak(tr))


def test_plant_draws_careful_safe_fast_stops():
    rng = np.random.default_rng(3)
    sets = [sample_params(CFG, rng, "plant") for _ in range(5)]
    with PeelEnv(CFG, source="plant", seed=0) as env:
        careful = [run_episode(env, constant(1.0), seed=10 + i, params=p)
                   for i, p in enumerate(sets)]
        fast = [run_episode(env, constant(8.0), seed=20 + i, params=p)
                for i, p in enumerate(sets)]
    assert [t.outcome for t in careful] == ["done"] * 5
    assert max(peak(t) for t in careful) < F_PRE
    # the planner's top speed (8 mm/s) stops most substrates (6 of 8 draws of seed 3)
    stopped = [t for t in fast if t.outcome == "safety_stop"]
    assert len(stopped) >= 3
    assert all(t.q[-1] < CFG.task.q_ter_mm for t in stopped)
