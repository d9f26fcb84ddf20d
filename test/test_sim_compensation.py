"""Force compensation (Eq. 17-22) against hand-computed values."""

import math

import pytest

from peel_sim_node import compensation as comp


def test_eq18_inertia_by_hand():
    # b = 2 mm, h = 0.5 mm: I = 2 * 0.125 / 12 = 0.0208333 mm^4
    assert comp.bending_inertia(2.0, 0.5) == pytest.approx(0.25 / 12.0, rel=1e-12)


def test_eq19_equals_eq17_and_hand_value():
    # E = 70000 N/mm^2, b = 2, h = 0.5, phi = 0.02 rad, L_p = 20 mm
    # Eq. 19: 70000 * 2 * 0.125 * 0.02 / (6 * 20) = 350 / 120 = 2.916666 N
    fb = comp.f_bend(70000.0, 2.0, 0.5, 0.02, 20.0)
    assert fb == pytest.approx(2.9166666667, rel=1e-9)
    assert comp.f_bend_eq17(70000.0, comp.bending_inertia(2.0, 0.5), 0.02, 20.0) == pytest.approx(fb)


def test_eq20_polynomial_by_hand():
    # v = 2 mm/s, phi = 10 deg:
    # 0.1623 + 0.03668 - 0.01579 - 0.0014104 - 0.00013414 + 0.0009326 = 0.18257806
    assert comp.f_peel(2.0, 10.0) == pytest.approx(0.18257806, abs=1e-8)
    assert comp.f_peel(0.0, 0.0) == pytest.approx(0.1623)


def test_eq21_22_by_hand():
    fx, fz = comp.compensate(e_n_per_mm2=70000.0, b_mm=2.0, h_mm=0.5, alpha_deg=30.0,
                             phi_rad=math.radians(10.0), lp_mm=20.0, v_mmps=2.0)
    fb = 70000.0 * 2.0 * 0.125 * math.radians(10.0) / 120.0  # 25.4527 N
    assert fx == pytest.approx(fb * 0.5, rel=1e-9)
    assert fz == pytest.approx(fb * math.sqrt(3) / 2 + 0.18257806, rel=1e-7)


def test_geometry_and_bad_length():
    phi, lp = comp.desorption_geometry(0.5, 10.0, 15.0)
    assert lp == 25.0
    assert phi == pytest.approx(math.atan(0.02))
    with pytest.raises(ValueError, match="L_p"):
        comp.f_bend(70000.0, 2.0, 0.5, 0.02, 0.0)


def hoisted_compensation(e: float, b: float, h: float, alpha_deg: float, phi: float, lp: float,
                         v: float, phi_deg: bool) -> tuple[float, float]:
    """The env's former inline copy of Eq. 19-22 (sin/cos of alpha hoisted out of the step)."""
    alpha = math.radians(alpha_deg)
    sin_a, cos_a = math.sin(alpha), math.cos(alpha)
    fb = comp.f_bend(e, b, h, phi, lp)
    fp = float(comp.f_peel(v, math.degrees(phi) if phi_deg else phi))
    return fb * sin_a, fb * cos_a + fp


@pytest.mark.parametrize("phi_deg", [True, False])
def test_compensate_equals_the_formerly_inlined_copy_bit_for_bit(phi_deg):
    """The simulator calls compensate(); its numbers are those of the copy it replaced."""
    import numpy as np

    rng = np.random.default_rng(17)
    for _ in range(200):
        e, b, h = rng.uniform(1e3, 1e5), rng.uniform(0.5, 5.0), rng.uniform(0.1, 1.5)
        alpha, phi = rng.uniform(0.0, 90.0), rng.uniform(0.0, 0.3)
        lp, v = rng.uniform(1.0, 80.0), rng.uniform(0.0, 20.0)
        got = comp.compensate(e_n_per_mm2=e, b_mm=b, h_mm=h, alpha_deg=alpha, phi_rad=phi,
                              lp_mm=lp, v_mmps=v, phi_unit_deg=phi_deg)
        assert got == hoisted_compensation(e, b, h, alpha, phi, lp, v, phi_deg)


def test_env_runs_compensate(monkeypatch):
    """PeelEnv's measured forces go through compensation.compensate (no copy of Eq. 21-22)."""
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv

    calls = []
    real = comp.compensate

    def spy(**kw):
        calls.append(kw)
        return real(**kw)

    monkeypatch.setattr(comp, "compensate", spy)
    with PeelEnv(load_sim_config(), source="sim", seed=1) as env:
        env.reset(seed=1)
        env.step(5.0)
    assert calls and {"alpha_deg", "phi_rad", "lp_mm", "v_mmps"} <= set(calls[0])
