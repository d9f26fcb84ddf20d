"""PeelEnv physics: stick-slip, parameter effects, episode rules, oracle rollout, plant."""

import numpy as np
import pytest

from peel_sim_node.config import load_sim_config
from peel_sim_node.effects import EffectAction, EffectState
from peel_sim_node.env import PeelEnv, sample_params
from peel_sim_node.episode import run_episode

CFG = load_sim_config()
N_TILES = CFG.scene.n_tiles


def flat_params(friction=0.9, stiffness=12000.0, damping=1000.0):
    p = {"friction": friction, "stiffness": stiffness, "damping": damping}
    p.update({f"tile_{i}": 1.0 for i in range(N_TILES)})
    return p


def const_run(params, u=2.0, n=60, seed=0, cfg=CFG, source="sim", effects=(), blade=False):
    with PeelEnv(cfg, seed=seed, params=params, source=source, effects=effects) as env:
        env.reset(seed=seed)
        for _ in range(n):
            if env.done:
                break
            env.step(u)
        return (env.history, env.blade_q_mm) if blade else env.history


def test_stick_slip_in_force_signal():
    h, blade_q = const_run(flat_params(), u=1.5, n=100, blade=True)
    # the robot's measured velocity scatters around the command (Eq. 2) ...
    assert abs(h.v[20:].mean() - 1.5) < 0.2
    # ... while the blade behind the compliance alternates between sticking (v ~ 0) and
    # slipping (v >> u)
    v = (np.diff(blade_q) / 0.1)[19:]
    assert np.mean(np.abs(v) < 0.2) > 0.3
    assert v.max() > 3 * 1.5
    # force builds while it sticks and drops when it slips: repeated drops of > 1 N
    dfx = np.diff(h.fx[20:])
    drops = dfx < -1.0
    assert drops.sum() >= 5
    # drops coincide with slips
    slips = v[1:] > 1.5
    assert np.mean(slips[drops]) > 0.8


@pytest.mark.parametrize("name,low,high", [("friction", 0.6, 1.0),
                                           ("stiffness", 8000.0, 16000.0),
                                           ("damping", 600.0, 1400.0)])
def test_higher_parameter_gives_higher_mean_fx(name, low, high):
    lo = const_run({**flat_params(), name: low}, u=3.0, n=60)
    hi = const_run({**flat_params(), name: high}, u=3.0, n=60)
    assert hi.fx[10:].mean() > lo.fx[10:].mean() + 0.3


def test_forces_rise_with_speed_and_paper_magnitudes():
    slow = const_run(flat_params(), u=2.5, n=200)
    fast = const_run(flat_params(), u=6.0, n=200)
    assert slow.outcome == "done"
    assert 7.0 < slow.fx.mean() < 13.0 and 4.0 < slow.fz.mean() < 9.0
    assert fast.fz[5:].mean() > slow.fz[5:].mean() + 2.0


def test_prewarning_stop():
    h = const_run(flat_params(friction=1.0, stiffness=16000, damping=1400), u=8.0, n=200)
    assert h.outcome == "safety_stop"
    last = max(abs(h.fx[-1]), abs(h.fz[-1]))
    assert last >= CFG.task.f_prewarn_n
    assert np.all(np.maximum(np.abs(h.fx[:-1]), np.abs(h.fz[:-1])) < CFG.task.f_prewarn_n)
    assert h.q[-1] < CFG.task.q_ter_mm


def test_timeout_and_done():
    cfg = load_sim_config({"task.t_max_s": 2.0})
    h = const_run(flat_params(), u=1.0, n=1000, cfg=cfg)
    assert h.outcome == "timeout"
    assert h.t[-1] == pytest.approx(2.0)
    cfg = load_sim_config({"task.q_ter_mm": 3.0})
    h = const_run(flat_params(), u=3.0, n=1000, cfg=cfg)
    assert h.outcome == "done" and h.q[-1] >= 3.0 and h.q[-2] < 3.0


def test_run_episode_and_history_layout():
    with PeelEnv(CFG, seed=5) as env:
        calls = []

        def policy(hist):
            calls.append(len(hist))
            return 3.0

        tr = run_episode(env, policy, seed=5)
    assert tr.outcome in ("done", "safety_stop")
    assert calls[:3] == [1, 6, 11]  # every 5 samples (0.5 s)
    assert tr.t[0] == 0.0 and tr.q[0] == 0.0
    assert np.allclose(np.diff(tr.t), 0.1)
    assert np.allclose(tr.v[1:], np.diff(tr.q) / 0.1)
    assert np.all(tr.u[:-1] == 3.0)
    assert set(tr.params) >= {"friction", "stiffness", "damping"}


def test_same_seed_same_data_and_different_seed_differs():
    a = const_run(None, u=2.0, n=40, seed=11)
    b = const_run(None, u=2.0, n=40, seed=11)
    c = const_run(None, u=2.0, n=40, seed=12)
    assert np.array_equal(a.as_array(), b.as_array(), equal_nan=True)
    assert a.params == b.params and a.params != c.params


def test_rollout_is_noise_free_truth_and_leaves_env_unchanged():
    cfg = load_sim_config({"noise.force_sigma_n": 0.0, "noise.force_bias_sigma_n": 0.0,
                           "noise.velocity_sigma_mmps": 0.0, "noise.force_resolution_n": 0.0})
    env = PeelEnv(cfg, seed=3)
    twin = PeelEnv(cfg, seed=3)
    for _ in range(15):
        env.step(2.5)
        twin.step(2.5)
    v = np.array([[2.0] * 8, [6.0] * 8])
    out = env.rollout(v)
    assert out.shape == (2, 8, 3)
    assert out[1, -1, 0] > out[0, -1, 0]  # faster goes further
    # with noise off, the rollout equals what stepping the twin produces
    for _ in range(8):
        twin.step(2.0)
    h = twin.history
    assert np.allclose(out[0, :, 0], h.q[-8:])
    assert np.allclose(out[0, :, 1], h.fx[-8:])
    assert np.allclose(out[0, :, 2], h.fz[-8:])
    # the env itself did not move
    assert len(env.history) == 16
    for _ in range(8):
        env.step(2.0)
    assert np.array_equal(env.history.fx, h.fx)
    env.close()
    twin.close()


def test_plant_differs_from_sim():
    # plant severity level 1 (docs/simulator.md); the other levels: test_sim_plant_levels.py
    cfg1 = load_sim_config({"plant.level": 1})
    rng = np.random.default_rng(0)
    sim = [sample_params(cfg1, rng, "sim") for _ in range(200)]
    plant = [sample_params(cfg1, rng, "plant") for _ in range(200)]

    def mean(sets, name):
        return np.mean([p[name] for p in sets])

    # a stickier, softer, less viscous pad
    assert mean(plant, "friction") > mean(sim, "friction") + 0.05
    assert mean(plant, "stiffness") < mean(sim, "stiffness") - 1000.0
    assert mean(plant, "damping") < mean(sim, "damping") - 250.0
    # same physical parameters: declared effects (residual vacuum, lag, drift) still differ
    p = flat_params()
    hs = const_run(p, u=2.0, n=30, source="sim", seed=1)
    hp = const_run(p, u=2.0, n=30, source="plant", seed=1, cfg=cfg1)
    assert hp.fz[1:10].mean() > hs.fz[1:10].mean() + 1.0  # residual vacuum near C


def test_injected_effect_shows_in_data_and_rollout():
    def sticky(s: EffectState) -> EffectAction:
        return EffectAction(load_n=4.0 if s.q_mm >= 2.0 else 0.0)

    p = flat_params(friction=0.7, stiffness=9000.0, damping=700.0)
    base = const_run(p, u=1.5, n=60, source="plant", seed=2)
    inj = const_run(p, u=1.5, n=60, source="plant", seed=2, effects=[sticky])
    n = min(len(base), len(inj))
    before = base.q[:n] < 1.5
    after = (base.q[:n] > 2.5) & (inj.q[:n] > 2.5)
    assert before.sum() >= 5 and after.sum() >= 5
    assert np.allclose(base.fz[:n][before], inj.fz[:n][before])
    # +4 N of load: F_RZ rises by less than 4 N because the compliant blade sinks deeper into
    # the pad, which lowers the glass's lift and its bending force (Eq. 19)
    assert inj.fz[:n][after].mean() > base.fz[:n][after].mean() + 1.5

    def always(s: EffectState) -> EffectAction:
        return EffectAction(load_n=4.0)

    with PeelEnv(CFG, seed=2, params=p, source="plant", effects=[always]) as env:
        for _ in range(20):
            env.step(1.5)
        out_inj = env.rollout(np.full((1, 5), 2.0))
    with PeelEnv(CFG, seed=2, params=p, source="plant") as env:
        for _ in range(20):
            env.step(1.5)
        out_base = env.rollout(np.full((1, 5), 2.0))
    assert out_inj[0, :, 2].mean() > out_base[0, :, 2].mean() + 1.5
