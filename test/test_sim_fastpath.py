"""The optimised hot paths compute exactly what their plain forms compute (bit for bit)."""

import math

import numpy as np
import pytest

from peel_sim_node.config import load_sim_config
from peel_sim_node.effects import EffectAction, EffectState
from peel_sim_node.env import PeelEnv
from peel_sim_node.noise import quantise

CFG = load_sim_config()
QUIET = load_sim_config({"noise.force_sigma_n": 0.0, "noise.force_bias_sigma_n": 0.0,
                         "noise.velocity_sigma_mmps": 0.0, "noise.force_resolution_n": 0.0,
                         "plant.drift_n_per_sqrt_s": 0.0})
CMDS = [1.0, 2.5, 4.0, 6.0, 3.0, 0.5, 8.0, 2.0]


def bits(x):
    return np.asarray(x, dtype="<f8").tobytes()


def test_quantise_equals_numpy_round():
    res = 0.01
    edge = [0.0, -0.0, 0.004, -0.004, 0.005, -0.005, 0.015, -0.025, 12.345, -7.125, 1e300,
            -1e300, 2.0**60, math.inf, -math.inf]
    rand = np.random.default_rng(0).normal(0.0, 15.0, 2000).tolist()
    for x in edge + rand:
        ref = float(np.round(np.array([x]) / res)[0] * res)
        assert bits(quantise(x, res)) == bits(ref), x
    assert math.isnan(quantise(math.nan, res))


def sticky(s: EffectState) -> EffectAction:
    return EffectAction(load_n=2.0 if s.q_mm > 3.0 else 0.0, resist_n=0.5 * (s.q_mm > 5.0),
                        v_scale=0.9)


def plain_substeps(env):
    """The engine steps of a sample written with ``_engine_step`` (the plain form)."""
    def run(target, resist_n, load_n):
        act = EffectAction(load_n=load_n, resist_n=resist_n)
        d = env.d
        for _ in range(env._nsub):
            d.v_robot += (target - d.v_robot) * env._a_lag
            env._engine_step(act, d.v_robot)
    return run


@pytest.mark.parametrize("source,effects", [("sim", ()), ("plant", (sticky,))])
def test_hot_loop_equals_plain_engine_step(source, effects):
    hist = []
    for plain in (False, True):
        with PeelEnv(CFG, source=source, seed=9, effects=effects) as env:
            if plain:
                env._substeps = plain_substeps(env)
            for k in range(60):
                if env.done:
                    break
                env.step(CMDS[(k // 5) % len(CMDS)])
            hist.append(env.history.as_array())
    assert len(hist[0]) > 40
    assert bits(hist[0]) == bits(hist[1])


def test_plant_rollout_is_the_plant_stepped_without_noise():
    """Lag, residual vacuum and an injected effect: the oracle equals stepping a twin."""
    env = PeelEnv(QUIET, source="plant", seed=6, effects=[sticky])
    twin = PeelEnv(QUIET, source="plant", seed=6, effects=[sticky])
    for k in range(25):
        env.step(CMDS[k // 5])
        twin.step(CMDS[k // 5])
    v = np.array([[3.0] * 10, np.linspace(1.0, 6.0, 10)])
    out = env.rollout(v)
    for u in v[1]:
        twin.step(u)
    h = twin.history
    assert bits(out[1, :, 0]) == bits(h.q[-10:])
    assert bits(out[1, :, 1]) == bits(h.fx[-10:])
    assert bits(out[1, :, 2]) == bits(h.fz[-10:])
    # and the env itself carries on as if no rollout had happened
    for u in v[1]:
        env.step(u)
    assert bits(env.history.as_array()) == bits(h.as_array())
    env.close()
    twin.close()
