"""The output-error fit of ``peel residual`` (``peel_residual.output_error``, docs/residual.md).

Clean simulator tasks (exploratory command profiles, data seed 3; the report's seeds are
others) with the shipped, simulator-trained model, an effect added on the measurement side.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from residual_helpers import generate_tasks

from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_model.compensated import corrected_model
from peel_model.effect_terms import Candidate, Term
from peel_residual import output_error as OE
from peel_residual import predict as P
from peel_residual.analysis import OPEN_LOOP, analyse
from peel_residual.config import load_residual_config
from peel_residual.data import horizons
from peel_residual.decide import open_loop_rmse
from peel_residual.inject import Injection
from peel_residual.study import ceiling


@pytest.fixture(scope="module")
def model():
    torch.set_num_threads(1)
    return load_checkpoint(shipped_checkpoint())


@pytest.fixture(scope="module")
def cfg():
    return load_residual_config()


@pytest.fixture(scope="module")
def sim8():
    return generate_tasks("sim", n=8, seed=3)


def _named(result) -> dict[str, set[tuple[str, str]]]:
    return {g: {(f.candidate.family, f.channel) for f in tr.findings}
            for g, tr in result.traces.items()}


def test_the_response_predicts_the_rollouts_change_under_an_effect_sized_term(sim8, model) -> None:
    """J c (the secant over a 1 N term) against the compensated model's rollout with a 1.5 N
    term on F_RZ: the same change on both channels (the term on F_RZ moves F_RX through
    f_theta), and the coefficient read back within 15 %."""
    hz = horizons(sim8, model.h, 25, 10)
    cand = Candidate("sensor_offset")
    base, resp = OE.open_loop_responses(model, hz, [cand], 0.1)
    assert set(resp) == {("sensor_offset", "fx"), ("sensor_offset", "fz")}
    J = resp[("sensor_offset", "fz")][1][..., 0]  # [n, S, 2]
    exact = P.open_loop(corrected_model(model, [Term(cand, "fz", (1.5,))], 0.1), hz) - base
    keep = OE.row_mask(hz)
    a, b = J[keep].ravel(), exact[keep].ravel()
    c = float(a @ b / (a @ a))  # the coefficient the secant reads off the exact change
    assert c == pytest.approx(1.5, rel=0.15)
    for ch in range(2):  # not smooth per horizon (module docstring), but the same change
        a, b = 1.5 * J[..., ch][keep], exact[..., ch][keep]
        assert 1 - np.sum((b - a) ** 2) / np.sum((b - b.mean()) ** 2) > 0.5
    steps = OE.row_steps(hz, keep)
    assert len(steps) == keep.sum()
    n, s = np.nonzero(keep)
    assert np.array_equal(steps.f_next, hz.rows[n, model.h + s, 2:4])


def test_a_drag_the_one_step_fit_misses_is_named_open_loop(sim8, model, cfg) -> None:
    data = Injection("viscous_drag", "fz", 1.5).apply(sim8)
    one_step = analyse(data, model, cfg)  # the default: the one-step fit only
    assert not cfg.open_loop_fit
    assert not any(one_step.traces["force"].findings), _named(one_step)
    both = analyse(data, model, replace(cfg, open_loop_fit=True))
    assert ("viscous_drag", "fz") in _named(both)[OPEN_LOOP], _named(both)
    drag = next(f for f in both.traces[OPEN_LOOP].findings if f.candidate.family == "viscous_drag")
    assert drag.coef[0] > 0  # +1.5 N at 6 mm/s: 0.25 N per mm/s injected
    assert both.rmse_after["fz"]["open_loop"] < both.rmse_before["fz"]["open_loop"]


def test_an_effect_the_open_loop_does_not_show_is_not_claimed(sim8, model, cfg) -> None:
    """A 1.5 N F_RX offset: the model carries its F_RX history through the horizon, so no
    correction could lower the open-loop error (the ceiling is about 1) and nothing is named."""
    data = Injection("sensor_offset", "fx", 1.5).apply(sim8)
    assert ceiling(model, sim8, data, cfg)["fx"] > 0.95
    r = analyse(data, model, replace(cfg, open_loop_fit=True))
    assert not any(tr.findings for g, tr in r.traces.items() if g != "v"), _named(r)


def test_the_ceiling_is_the_error_left_by_the_injected_term_itself(sim8, model, cfg) -> None:
    """``study.ceiling``: clean over injected open-loop RMSE equals what the compensated model
    with the exact injected term leaves on the injected tasks (module docstring of study)."""
    data = Injection("sensor_offset", "fz", 1.5).apply(sim8)
    hz = horizons(data, model.h, cfg.horizon_steps, cfg.stride)
    exact = corrected_model(model, [Term(Candidate("sensor_offset"), "fz", (1.5,))], 0.1)
    best = open_loop_rmse(exact, hz)["fz"] / open_loop_rmse(model, hz)["fz"]
    assert ceiling(model, sim8, data, cfg)["fz"] == pytest.approx(best, rel=1e-3)
    assert best < 0.6
