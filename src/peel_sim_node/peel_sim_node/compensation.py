"""Force compensation of the simulated contact force, paper section 3.2.2 (Eq. 17-22).

The glass substrate is elastic and held by vacuum, which a rigid-body engine does not model.
The blade's force on the glass bends it (shear force ``f_bend``, cantilever, Eq. 17-19) and
supplies the critical peel load ``f_peel`` (Eq. 20). Both are added to the engine's forces:

    f_bend = 2 E I phi / L_p,  I = b h^3 / 12   =>   f_bend = E b h^3 phi / (6 L_p)   (17-19)
    f_peel = 0.1623 + 0.01834 v - 0.001579 phi - 0.0003526 v^2
             - 6.707e-6 v phi + 9.326e-6 phi^2                                       (20)
    F~_RX = f_bend sin(alpha)                                                        (21)
    F~_RZ = f_bend cos(alpha) + f_peel                                               (22)

Units (our choice, the paper leaves them open): E in N/mm^2, b, h, L_p in mm, so f_bend is in
N with phi in rad (Eq. 19 is a small-angle beam formula). Eq. 20 takes v in mm/s and phi in
degrees: with phi in degrees the phi terms are of the same order as the v terms over the
physical range (a few degrees, a few mm/s), and the polynomial stays positive (~0.16-0.3 N);
with phi in rad they would be negligible. ``phi_unit_deg=False`` switches Eq. 20 to rad.
"""

from __future__ import annotations

import math

import numpy as np


def bending_inertia(b_mm: float, h_mm: float) -> float:
    """Eq. 18: I = b h^3 / 12 of the rectangular glass cross-section, mm^4."""
    return b_mm * h_mm**3 / 12.0


def f_bend(e_n_per_mm2: float, b_mm: float, h_mm: float, phi_rad: float, lp_mm: float) -> float:
    """Eq. 19: shear force bending the peeled glass, f_bend = E b h^3 phi / (6 L_p), N."""
    if lp_mm <= 0.0:
        raise ValueError(f"peeled length L_p must be > 0 mm, got {lp_mm!r}")
    return e_n_per_mm2 * b_mm * h_mm**3 * phi_rad / (6.0 * lp_mm)


def f_bend_eq17(e_n_per_mm2: float, inertia_mm4: float, phi_rad: float, lp_mm: float) -> float:
    """Eq. 17: f_bend = 2 E I phi / L_p (N), the form before substituting Eq. 18."""
    return 2.0 * e_n_per_mm2 * inertia_mm4 * phi_rad / lp_mm


def f_peel(v_mmps: float | np.ndarray, phi: float | np.ndarray) -> float | np.ndarray:
    """Eq. 20: critical peel force (N) as the binary quadratic polynomial in v and phi."""
    return (
        0.1623
        + 0.01834 * v_mmps
        - 0.001579 * phi
        - 0.0003526 * v_mmps**2
        - 6.707e-6 * v_mmps * phi
        + 9.326e-6 * phi**2
    )


def desorption_geometry(lift_mm: float, q_mm: float, lp0_mm: float) -> tuple[float, float]:
    """Peeled length L_p = L_p0 + q and desorption angle phi = atan(lift / L_p) (rad).

    ``lift_mm`` is the substrate's height above the pad at the blade, read from the engine."""
    lp = lp0_mm + max(q_mm, 0.0)
    return math.atan2(max(lift_mm, 0.0), lp), lp


def compensate(
    *,
    e_n_per_mm2: float,
    b_mm: float,
    h_mm: float,
    alpha_deg: float,
    phi_rad: float,
    lp_mm: float,
    v_mmps: float,
    phi_unit_deg: bool = True,
) -> tuple[float, float]:
    """Eq. 21-22: the compensation (F~_RX, F~_RZ) in N added to the engine's forces."""
    fb = f_bend(e_n_per_mm2, b_mm, h_mm, phi_rad, lp_mm)
    phi20 = math.degrees(phi_rad) if phi_unit_deg else phi_rad
    fp = float(f_peel(v_mmps, phi20))
    a = math.radians(alpha_deg)
    return fb * math.sin(a), fb * math.cos(a) + fp
