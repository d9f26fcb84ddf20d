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
