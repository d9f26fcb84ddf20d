"""Plant severity levels, sequences and the compliant blade (docs/simulator.md): every level
builds and differs from the simulator as documented; the sequences change the pad as
documented; the indentation psi follows the vertical load."""

import numpy as np
import pytest

from peel_msgs_py.errors import ParameterError, PeelError
from peel_sim_node.config import load_sim_config
from peel_sim_node.effects import EffectAction, ResidualVacuum
from peel_sim_node.env import PeelEnv, sample_params
from peel_sim_node.plant import (
    LEVELS,
    SEQUENCES,
    check_level,
    plant_spec,
    sequence_params,
)

CFG = load_sim_config()


def params(**kw):
    p = {"friction": 0.8, "stiffness": 11000.0, "damping": 600.0}
    p.update(kw)
    return p


def run(p, u, n, level, seed=1, cfg=CFG, effects=()):
    with PeelEnv(cfg, source="plant", level=level, seed=seed, params=p,
                 effects=effects) as env:
        for _ in range(n):
            if env.done:
                break
            env.step(u)
        return env.history


def drops(fx, thr=1.0):
    d = np.diff(fx)
    return d[d < -thr]


def test_level_table_and_default():
    assert LEVELS == (0, 1, 2, 3)
    assert CFG.plant.level == max(LEVELS)  # the strongest level is the default plant
    assert [plant_spec(CFG, lv).level for lv in LEVELS] == list(LEVELS)
    for bad in (-1, 4, 1.5, "3", True):
        with pytest.raises(PeelError, match="plant level"):
            check_level(bad)
    with pytest.raises(ParameterError, match=r"plant\.level"):
        load_sim_config({"plant.level": 7})


def test_level0_is_the_simulator_bit_for_bit():
    p = sample_params(CFG, np.random.default_rng(5), "sim")
    assert sample_params(CFG, np.random.default_rng(5), "plant", 0) == p
    with PeelEnv(CFG, source="sim", seed=3, params=p) as a, \
            PeelEnv(CFG, source="plant", level=0, seed=3, params=p) as b:
        for u in (1.0, 3.0, 6.0, 2.0) * 5:
            a.step(u)
            b.step(u)
        assert np.array_equal(a.history.as_array(), b.history.as_array())
        assert b.effects == [] and b.level == 0


def test_level1_is_the_documented_plant():
    s = plant_spec(CFG, 1)
    p = CFG.plant
    assert s.friction == (p.friction_low, p.friction_high)
    assert s.damping == (p.damping_low, p.damping_high)
    assert (s.actuator_lag_s, s.drift_n_per_sqrt_s) == (p.actuator_lag_s, p.drift_n_per_sqrt_s)
    assert s.effects() == [ResidualVacuum(p.residual_vacuum_n, p.residual_length_mm)]
    # the residual vacuum near C shows against level 0 on the same pad
    h0, h1 = run(params(), 2.0, 30, 0), run(params(), 2.0, 30, 1)
    assert h1.fz[1:10].mean() > h0.fz[1:10].mean() + 0.5


def test_level2_forces_rise_less_with_speed_than_level1():
    s1, s2 = plant_spec(CFG, 1), plant_spec(CFG, 2)
    assert s2.damping[1] < s1.damping[0] + 200.0 and s2.rate_gain_scale < 1.0
    draws = [sample_params(CFG, np.random.default_rng(k), "plant", 2) for k in range(50)]
    assert all(s2.damping[0] <= d["damping"] <= s2.damping[1] for d in draws)
    p = params(damping=800.0)

    def rise(level):
        slow, fast = run(p, 1.0, 150, level), run(p, 7.0, 40, level)
        return fast.fz[20:].mean() - slow.fz[60:].mean()

    assert rise(2) < rise(1) - 0.5


def test_level3_wet_pad_lower_friction_weaker_stick_slip():
    s2, s3 = plant_spec(CFG, 2), plant_spec(CFG, 3)
    assert s3.friction[1] < s2.friction[0]
    assert s3.static_friction_ratio < CFG.scene.static_friction_ratio
    assert s3.actuator_lag_s > s2.actuator_lag_s
    draws = [sample_params(CFG, np.random.default_rng(k), "plant", 3) for k in range(50)]
    assert max(d["friction"] for d in draws) <= s3.friction[1]
    # same pad parameters: the smaller static/kinetic ratio gives smaller stick-slip drops
    p = params(friction=0.8)
    d2, d3 = drops(run(p, 1.0, 150, 2).fx), drops(run(p, 1.0, 150, 3).fx)
    assert d3.size == 0 or -d3.mean() < -d2.mean()


def test_sequences():
    p = params(friction=0.8)
    sq = CFG.sequence
    assert SEQUENCES == ("stationary", "drift", "batch-switch")
    for k in (1, 7, 20):
        assert sequence_params(CFG, p, k, "stationary") == p
    f = [sequence_params(CFG, p, k, "drift")["friction"] for k in range(1, 21)]
    assert f[0] == 0.8 and np.allclose(np.diff(f), 0.8 * sq.drift_friction_per_task)
    before = sequence_params(CFG, p, sq.switch_task - 1, "batch-switch")
    after = sequence_params(CFG, p, sq.switch_task, "batch-switch")
    assert before == p
    assert after["stiffness"] == pytest.approx(p["stiffness"] * sq.switch_stiffness_scale)
    assert after["damping"] == pytest.approx(p["damping"] * sq.switch_damping_scale)
    assert after["friction"] == pytest.approx(p["friction"] * sq.switch_friction_scale)
    with pytest.raises(PeelError, match="sequence"):
        sequence_params(CFG, p, 1, "wobble")
    # the worn pad really is harder to peel: mean F_RX of task 20 above task 1
    h1 = run(sequence_params(CFG, p, 1, "drift"), 3.0, 40, 3)
    h20 = run(sequence_params(CFG, p, 20, "drift"), 3.0, 40, 3)
    assert h20.fx[5:].mean() > h1.fx[5:].mean() + 0.5


def test_psi_varies_with_vertical_load():
    p = params(damping=1000.0)
    with PeelEnv(CFG, source="sim", seed=2, params=p) as env:
        for k in range(60):  # careful start, then fast: the peel-rate load grows
            if not env.done:
                env.step(1.0 if k < 30 else 6.0)
        h = env.history
    # psi spans a range and follows F_RZ (the vertical load) sample by sample
    assert h.psi.max() - h.psi.min() > 0.08
    assert np.corrcoef(h.psi[5:], h.fz[5:])[0, 1] > 0.8

    def heavy(_s):
        return EffectAction(load_n=5.0)

    hh = run(p, 1.0, 60, 0, seed=2, effects=[heavy])
    h1 = run(p, 1.0, 60, 0, seed=2)
    assert hh.psi[10:].mean() > h1.psi[10:].mean() + 0.05
    # a rigid tool holds psi at the press depth
    rigid = load_sim_config({"scene.tool_compliance_z_mm_per_n": 0.0,
                             "scene.press_depth_mm": 0.125})
    hr = run(p, 1.0, 60, 0, seed=2, cfg=rigid)
    assert np.ptp(hr.psi) < 1e-9 and hr.psi[0] == pytest.approx(0.125, abs=1e-6)
