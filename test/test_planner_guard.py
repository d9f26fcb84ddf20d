"""The guard of the force limit under model error (docs/planner.md, Eq. M1-M4): the margin
from the measured force error (a conformal quantile), the slowest sequence among the samples,
the check of the command and its fallback, on a small deterministic plant whose model is wrong
by a known amount."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from peel_msgs_py.errors import ParameterError
from peel_msgs_py.task import Sample
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import (
    GUARDED,
    UNGUARDED,
    MarginConfig,
    PlannerConfig,
    load_planner_config,
)
from peel_planner_node.control_loop import ControlLoop, guard_line
from peel_planner_node.cost import BarrierCritic, Cost
from peel_planner_node.guard import (
    ForceMargin,
    fallback_speed,
    first_period_forces,
    largest_safe,
    slowdown_speed,
)
from peel_planner_node.mppi import Planner

torch.set_num_threads(1)

DT = 0.1


def true_forces(q: torch.Tensor | float, v: torch.Tensor | float) -> tuple:
    """The test plant: F_RX = 4 + 1.6 v + 0.45 q (rises along the stroke), F_RZ = 3 + 0.2 v."""
    return 4.0 + 1.6 * v + 0.45 * q, 3.0 + 0.2 * v


class PlantModel:
    """Planner dynamics of the test plant, F_RX under-predicted by ``offset`` N (or scaled by
    ``scale``; ``fx``: a constant prediction)."""

    def __init__(self, offset: float = 0.0, fx: float | None = None, scale: float = 1.0) -> None:
        self.offset, self.fx, self.scale = offset, fx, scale

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        q = float(history.q[-1]) + DT * torch.cumsum(v, dim=1)
        fx, fz = true_forces(q, v)
        fx = torch.full_like(v, self.fx) if self.fx is not None else self.scale * fx - self.offset
        return torch.stack([q, fx, fz], dim=-1)


def config(**flat) -> PlannerConfig:
    """The guarded planner (GUARDED) in float64, with ``flat`` on top."""
    return PlannerConfig().replace(**{"mppi.dtype": "float64", **GUARDED, **flat})


def test_the_shipped_planner_has_the_guard_on() -> None:
    """config/peel_planner_node.yaml, the dataclass defaults and GUARDED agree."""
    for safety in (PlannerConfig().safety, load_planner_config().safety):
        assert (safety.margin.enabled, safety.margin.delta, safety.margin.init_n,
                safety.null_sample, safety.check.enabled, safety.fallback) == (
                    True, 0.2, 0.5, True, True, "least_force")
    assert PlannerConfig().replace(**GUARDED).safety == PlannerConfig().safety
    off = PlannerConfig().replace(**UNGUARDED).safety
    assert not (off.margin.enabled or off.null_sample or off.check.enabled)


def peel(planner: Planner, steps_per_plan: int = 5, t_max: float = 30.0) -> Trajectory:
    """Run the test plant under ``planner`` (velocity tracked exactly, no noise) until done,
    a 20 N prewarning or t_max; the trajectory carries the guard in its meta."""
    planner.reset()
    rows = [[0.0, 0.0, 0.0, 0.0, *true_forces(0.0, 0.0), np.nan]]
    while planner.stop is None and rows[-1][0] < t_max:
        u = planner.plan(Trajectory.from_array(np.asarray(rows)))
        for _ in range(steps_per_plan):
            t, q = rows[-1][0] + DT, rows[-1][1] + DT * u
            rows.append([t, q, u, u, *true_forces(q, u), np.nan])
    outcome = planner.stop.outcome if planner.stop else "timeout"
    return Trajectory.from_array(np.asarray(rows), outcome=outcome,
                                 meta={"planner_guard": planner.guard.as_dict()})


def peak(traj: Trajectory) -> float:
    return float(max(np.abs(traj.fx).max(), np.abs(traj.fz).max()))


# ---------------------------------------------------------------- Eq. M1
def test_margin_is_the_conformal_quantile_of_the_errors() -> None:
    """Eq. M1: m = the r-th smallest error, r = ceil((n + 1)(1 - delta)), clipped to
    [0, max_n]; init_n before min_count errors; max_n when r > n."""
    m = ForceMargin(MarginConfig(delta=0.25, window=7, min_count=3, init_n=1.5, max_n=5.0))
    assert m.value.tolist() == [1.5, 1.5]  # fewer than min_count errors: init_n
    # n = 3: r = ceil(4 * 0.75) = 3, the largest; RX errors 1, 2, -1; RZ exact
    m.observe(np.array([[11.0, 3.0], [12.0, 3.0], [9.0, 3.0]]),
              np.array([[10.0, 3.0], [10.0, 3.0], [10.0, 3.0]]))
    np.testing.assert_allclose(m.value, [2.0, 0.0])
    # n = 7: r = ceil(8 * 0.75) = 6: errors 1, 2, -1, 0.5, 3, 4, 1.5 -> sorted 6th = 3
    m.observe(np.array([[10.5, 3.0], [13.0, 3.0], [14.0, 3.0], [11.5, 3.0]]),
              np.full((4, 2), [10.0, 3.0]))
    np.testing.assert_allclose(m.value, [3.0, 0.0])
    m.observe(np.array([[30.0, 3.0]] * 2), np.array([[10.0, 3.0]] * 2))
    assert m.value[0] == 5.0  # the ceiling
    m.observe(np.full((7, 2), 10.0), np.full((7, 2), 11.0))  # over-predicted: no margin
    assert m.value.tolist() == [0.0, 0.0]
    tight = ForceMargin(MarginConfig(delta=0.01, window=20, min_count=5, init_n=0.0, max_n=4.0))
    tight.observe(np.zeros((20, 2)), np.zeros((20, 2)))
    assert tight.value.tolist() == [4.0, 4.0]  # r = ceil(21 * 0.99) = 21 > n: max_n
    off = ForceMargin(MarginConfig(enabled=False, init_n=2.0))
    off.observe(np.full((9, 2), 15.0), np.full((9, 2), 10.0))
    assert off.value.tolist() == [0.0, 0.0]


def test_margin_bounds_the_exceedance_at_delta() -> None:
    """The chance constraint of Eq. M2 on exchangeable errors: the next error exceeds m_a
    with probability at most delta (measured over 4000 draws, delta = 0.1, n = 20: the
    conformal bound's frequency is 1 - r/(n + 1) = 1/21 ~ 0.048)."""
    rng = np.random.default_rng(3)
    hits = 0
    for _ in range(4000):
        m = ForceMargin(MarginConfig(delta=0.1, window=20, min_count=10, max_n=100.0))
        e = rng.normal(1.0, 2.0, size=21)
        m.observe(e[:20, None].repeat(2, 1), np.zeros((20, 2)))
        hits += int(e[20] > m.value[0])
    assert 0.03 < hits / 4000 <= 0.1


def test_check_takes_the_zero_crossing_at_or_below_u_star() -> None:
    c = np.array([0.5, 1.5, 2.5, 3.5])
    assert largest_safe(c, np.array([-3.0, -2.0, -1.0, -0.5]), 3.2) == 3.2
    assert largest_safe(c, np.array([-3.0, -1.0, 1.0, 2.0]), 3.2) == pytest.approx(2.0)
    assert largest_safe(c, np.array([-3.0, -1.0, 1.0, 2.0]), 1.8) == 1.8
    assert largest_safe(c, np.array([0.1, 1.0, 2.0, 3.0]), 3.2) is None


def test_prediction_of_the_issued_command_is_interpolated_in_v0() -> None:
    v0 = np.array([2.0, 1.0, 1.0, 3.0])
    f = np.stack([np.full((5, 2), x * 10.0) for x in v0])
    np.testing.assert_allclose(first_period_forces(v0, f, 2.5), np.full((5, 2), 25.0))
    assert first_period_forces(v0, f, 0.0) is None


def test_tightened_barrier_is_the_barrier_at_zero_margin() -> None:
    b = BarrierCritic(PlannerConfig().cost.barrier)
    f = torch.linspace(0.0, 25.0, 60, dtype=torch.float64).reshape(10, 3, 2)
    torch.testing.assert_close(b.tightened(f, torch.zeros(2, dtype=torch.float64)),
                               b.sample_costs(type("R", (), {"forces": f, "margin": None})()))
    lim = b.tightened(torch.tensor([[[18.0, 0.0]]], dtype=torch.float64),
                      torch.tensor([2.0, 0.0], dtype=torch.float64))
    assert float(lim) == pytest.approx(8.0 + 10.0)  # 18 N is the limit 20 - 2: full cost


# ---------------------------------------------------------------- closed loop
@pytest.mark.parametrize("offset", [1.0, 2.0, 3.0])
def test_margin_grows_with_the_models_measured_error(offset: float) -> None:
    """F_RX under-predicted by a known offset: every error is the offset, so Eq. M1's
    quantile is exactly the offset (RZ, exact: 0)."""
    planner = Planner(PlantModel(offset), None, config(**{"safety.margin.max_n": 10.0}))
    traj = peel(planner, t_max=5.0)
    assert planner.margin.value[0] == pytest.approx(offset, abs=1e-6)
    assert planner.margin.value[1] == pytest.approx(0.0, abs=1e-6)
    assert traj.meta["planner_guard"]["margin_last_n"][0] == pytest.approx(offset, abs=1e-3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wrong_model_trips_the_prewarning_without_the_guard_and_not_with_it(seed: int) -> None:
    """A model 5.5 N under its plant: the planner without the guard runs into the 20 N
    prewarning; with it (margin 5.5 N, the measured error), on the same seeds, the peel
    finishes under the limit."""
    cfg = config(**{"mppi.seed": seed})
    bare = peel(Planner(PlantModel(5.5), None, cfg.replace(**UNGUARDED)))
    guarded = peel(Planner(PlantModel(5.5), None, cfg))
    assert bare.outcome == "safety_stop" and peak(bare) >= 20.0
    assert guarded.outcome == "done" and peak(guarded) < 20.0
    assert guarded.meta["planner_guard"]["margin_max_n"][0] == pytest.approx(5.5)
    assert guarded.meta["planner_guard"]["commands_reduced"] >= 1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scaled_model_margin_follows_the_error_and_holds_the_limit(seed: int) -> None:
    """A model predicting 70 % of F_RX: the error 0.3 F_RX grows along the stroke, the margin
    follows it (Eq. M1 on the window), the unguarded planner trips the prewarning and the
    guarded one, on the same seeds, finishes under 20 N."""
    cfg = config(**{"mppi.seed": seed})
    bare = peel(Planner(PlantModel(scale=0.7), None, cfg.replace(**UNGUARDED)))
    planner = Planner(PlantModel(scale=0.7), None, cfg)
    guarded = peel(planner)
    assert bare.outcome == "safety_stop" and peak(bare) >= 20.0
    assert guarded.outcome == "done" and peak(guarded) < 20.0
    rx = [m[0] for m in planner.guard.margins]  # per plan: init_n, then Eq. M1
    assert rx[:2] == [0.5, 0.5] and 0.5 < rx[2] < rx[-1] <= 0.3 * peak(guarded) + 1e-9
    assert guarded.meta["planner_guard"]["margin_last_n"] == pytest.approx([rx[-1], 0.0], abs=1e-4)


def test_correct_model_margin_shrinks_and_command_is_todays() -> None:
    """An exact model: the margin falls from init_n to 0 and every command equals the
    unguarded planner's within 0.1 mm/s: the check never binds below the limit and the
    slowest sequence gets a weight that matters only where the plan is near u_min already
    (here the last 0.5 s: 0.50 against 0.58 mm/s; before that within 0.04 mm/s)."""
    cfg = config(**{"mppi.seed": 4})
    guarded = peel(Planner(PlantModel(0.0), None, cfg))
    bare = peel(Planner(PlantModel(0.0), None, cfg.replace(**UNGUARDED)))
    g = guarded.meta["planner_guard"]
    assert g["margin_max_n"][0] == pytest.approx(0.5) and g["margin_last_n"] == [0.0, 0.0]
    assert g["fallbacks"] == 0 and g["commands_reduced"] == 0
    n = min(len(guarded), len(bare))
    np.testing.assert_allclose(guarded.u[:n], bare.u[:n], atol=0.1)
    assert abs(guarded.t_cpl - bare.t_cpl) <= 0.5
    assert guarded.outcome == bare.outcome == "done"


def test_every_sample_unsafe_sends_the_fallback_and_counts_it() -> None:
    """A model that predicts 25 N whatever the speed: no sample is safe, the fallback (Eq. M4:
    the least-force candidate, here u_min since all are equal) goes out instead of the weighted
    mean, the blade keeps moving, and the trajectory meta counts it."""
    planner = Planner(PlantModel(fx=25.0), None, config())
    traj = peel(planner, t_max=2.0)
    assert np.all(traj.u[1:] == 0.5) and traj.q[-1] == pytest.approx(0.5 * traj.t[-1])
    assert planner.last["fallback"] and planner.last["u_star"] >= 0.5
    g = traj.meta["planner_guard"]
    assert g["fallbacks"] == g["plans"] == g["all_samples_unsafe"] >= 4
    assert float(planner.U.max()) == pytest.approx(0.5)  # the next plan starts from it


def test_fallback_is_the_least_force_candidate_or_u_min() -> None:
    c = np.array([0.5, 1.5, 2.5, 3.5])
    g = np.array([2.0, 1.0, 1.0, 3.0])
    assert fallback_speed(c, g, "least_force") == 1.5  # the lowest g, the slowest of equals
    assert fallback_speed(c, g, "u_min") == 0.5


def test_control_loop_logs_the_fallback_and_exposes_the_margin() -> None:
    cfg = config()
    loop = ControlLoop(cfg, PlantModel(fx=25.0), seed=0)
    assert loop.safety_report() is None
    answers = [loop.on_sample(Sample(k * 100_000_000, 0, 0.05 * k, 0.5, 4.0, 3.0))
               for k in range(6)]
    planned = [a for a in answers if a is not None]
    assert [a.u_mmps for a in planned] == [0.5, 0.5]
    assert "guard fallback" in planned[1].note and "sent 0.50 mm/s" in planned[1].note
    assert loop.guard["fallbacks"] == 2 and loop.margin_n == pytest.approx(0.5)
    report = json.loads(loop.safety_report())
    assert report["task"] == 0 and report["fallbacks"] == 2 and report["plans"] == 2
    stop = loop.on_sample(Sample(600_000_000, 0, 0.3, 0.5, 21.0, 3.0))
    assert stop is not None and "guard: 0 of 2 commands reduced" in stop.note
    assert "2 fallbacks" in stop.note


def test_the_slowest_sequence_is_weighted_with_the_samples() -> None:
    cfg = config(**{"mppi.n_samples": 6})
    planner = Planner(PlantModel(), Cost(cfg.cost), cfg)
    planner.plan(Trajectory.from_array(np.array([[0.0, 0, 0, 0, 4.0, 3.0, np.nan]])))
    v = planner.last["v"]
    assert v.shape == (7, 5) and torch.all(v[-1] == 0.5)
    assert planner.last["omega"].shape == (7,)
    off = Planner(PlantModel(), Cost(cfg.cost), cfg.replace(**{"safety.null_sample": False}))
    off.plan(Trajectory.from_array(np.array([[0.0, 0, 0, 0, 4.0, 3.0, np.nan]])))
    assert off.last["v"].shape == (6, 5)


def test_margin_widens_back_once_the_model_is_right() -> None:
    """Wrong by 2 N, then (model swapped) right: the margin rises to the 2 N error and falls
    back to 0 once the window (20 errors = 4 control periods) holds no more than
    n - r = 3 of the wrong model's errors (r = ceil(21 x 0.8) = 17)."""
    planner = Planner(PlantModel(2.0), None, config())
    rows = [[0.0, 0.0, 0.0, 0.0, *true_forces(0.0, 0.0), np.nan]]
    margins = []
    for k in range(10):
        if k == 4:
            planner.set_dynamics(PlantModel(0.0))
        u = planner.plan(Trajectory.from_array(np.asarray(rows)))
        margins.append(float(planner.last["margin"][0]))
        for _ in range(5):
            t, q = rows[-1][0] + DT, rows[-1][1] + DT * u
            rows.append([t, q, u, u, *true_forces(q, u), np.nan])
    assert margins[:2] == [0.5, 0.5] and margins[2:5] == pytest.approx([2.0] * 3)
    assert margins[8] == pytest.approx(0.0) and margins[9] == pytest.approx(0.0)
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(margins[4:]))


# ---------------------------------------------------------------- Eq. M5
def test_slowdown_scales_the_command_by_the_measured_peak() -> None:
    """Eq. M5: s = (20 - F_hat) / (20 - 17) clipped to [0, 1]; the command is at most
    s u_prev and never below u_min; below start_n nothing changes."""
    assert slowdown_speed(4.0, 6.0, 16.9, 0.5, 20.0, 17.0) == 4.0
    assert slowdown_speed(4.0, 6.0, 18.5, 0.5, 20.0, 17.0) == pytest.approx(3.0)  # s = 0.5
    assert slowdown_speed(2.0, 6.0, 18.5, 0.5, 20.0, 17.0) == 2.0  # already below s u_prev
    assert slowdown_speed(4.0, 6.0, 19.9, 0.5, 20.0, 17.0) == 0.5  # s u_prev = 0.2 < u_min
    assert slowdown_speed(4.0, None, 18.5, 0.5, 20.0, 17.0) == pytest.approx(2.0)  # s u_out
    assert slowdown_speed(4.0, 6.0, 25.0, 0.5, 20.0, 17.0) == 0.5


def test_slowdown_starts_below_the_prewarning_and_ships_off() -> None:
    """The shipped planner has Eq. M5 off; a start at or above f_prewarn is refused by name."""
    assert not load_planner_config().safety.slowdown.enabled
    assert not PlannerConfig().safety.slowdown.enabled
    with pytest.raises(ParameterError, match=r"safety\.slowdown\.start_n"):
        config(**{"safety.slowdown.start_n": 20.0})


def _history(fx_last_period: list[float], u: float) -> Trajectory:
    """One control period at speed ``u`` whose measured F_RX samples are ``fx_last_period``."""
    rows = [[0.0, 0.0, 0.0, u, 4.0, 3.0, np.nan]]
    for k, fx in enumerate(fx_last_period, start=1):
        rows.append([k * DT, k * DT * u, u, u, fx, 3.0, np.nan])
    return Trajectory.from_array(np.asarray(rows))


def test_slowdown_lowers_the_command_after_a_measured_peak_and_says_so() -> None:
    """After a period at 4 mm/s that measured 18.5 N (s = 0.5) the command is at most 2 mm/s,
    U is capped there, the guard counts it and the control loop's line names it; the same
    planner without Eq. M5, or after a period under start_n, sends the MPPI command."""
    on = config(**{"safety.slowdown.enabled": True, "mppi.seed": 3})
    quiet, peak = _history([10.0, 11.0, 12.0, 12.5, 13.0], 4.0), _history(
        [10.0, 11.0, 18.5, 12.5, 13.0], 4.0)
    planner = Planner(PlantModel(), None, on)
    plain = Planner(PlantModel(), None, config(**{"mppi.seed": 3}))

    def first(p: Planner, history: Trajectory) -> float:
        p.reset()
        p._u_prev = 4.0  # the command in force over the period of ``history``
        return p.plan(history)

    u_plain, u = first(plain, peak), first(planner, peak)
    assert u_plain > 2.0 and u == pytest.approx(2.0)
    assert planner.last["slowed"] and float(planner.U.max()) <= 2.0 + 1e-9
    assert planner.guard.as_dict()["commands_slowed"] == 1
    assert first(planner, quiet) == first(plain, quiet)
    assert planner.guard.as_dict()["commands_slowed"] == 0
    loop = ControlLoop(on, PlantModel(), seed=0)
    notes = [loop.on_sample(Sample(k * 100_000_000, 0, 0.4 * k, 4.0, fx, 3.0))
             for k, fx in enumerate([4.0, 10.0, 11.0, 18.5, 12.0, 12.0, 12.0])]
    slowed = [a.note for a in notes if a is not None and a.note and "slowdown" in a.note]
    assert slowed and "measured |F| >= 17 N" in slowed[0]


# ---------------------------------------------------------------- Eq. M7
class LateModel(PlantModel):
    """Exact over the first control period, F_RX under-predicted by ``late`` N from model
    step 6 of a rollout on (the error of a model that is right now and wrong later)."""

    def __init__(self, late: float) -> None:
        super().__init__()
        self.late = late

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        out = super().rollout(history, v)
        out[..., 1] -= self.late * (torch.arange(v.shape[1]) >= 5).to(out.dtype)
        return out


def _plans(planner: Planner, count: int) -> tuple[list[np.ndarray], list[float]]:
    """``count`` plans on the test plant with the trajectory's ``u`` as the control loop
    records it (the command in force over (t_k, t_k+1]); the margins in use and commands."""
    planner.reset()
    rows = [[0.0, 0.0, 0.0, 0.0, *true_forces(0.0, 0.0), np.nan]]
    margins, commands = [], []
    for _ in range(count):
        u = planner.plan(Trajectory.from_array(np.asarray(rows)))
        rows[-1][3] = u
        margins.append(planner.last["margin"].copy())
        commands.append(u)
        for _ in range(5):
            t, q = rows[-1][0] + DT, rows[-1][1] + DT * u
            rows.append([t, q, u, u, *true_forces(q, u), np.nan])
    return margins, commands


def test_horizon_margin_is_the_quantile_of_the_replayed_errors() -> None:
    """Eq. M7: a model exact over the first period but 2 N low from step 6 on gives Eq. M1 a
    zero margin; each replay adds 5 zero errors and 20 of 2 N, so with window 50 the quantile
    (r = ceil(51 x 0.8) = 41 of 50 sorted) is 2 N and sets the margin (counted in the meta);
    off (the shipped default), the margin stays Eq. M1's."""
    on = Planner(LateModel(2.0), None, config(**{"safety.margin.lead_enabled": True}))
    margins, _ = _plans(on, 12)
    assert on.margin.value[0] == pytest.approx(0.0, abs=1e-9)
    assert on.lead_margin.value.tolist() == pytest.approx([2.0, 0.0], abs=1e-9)
    assert margins[-1].tolist() == pytest.approx([2.0, 0.0], abs=1e-9)
    # the first replay needs H k = 25 samples behind it (plan 6, at 2.5 s); min_count = 10
    # errors are there at once
    assert [m[0] for m in margins] == pytest.approx([0.5, 0.5, 0.0, 0.0, 0.0] + [2.0] * 7)
    assert on.guard.as_dict()["margin_from_horizon"] == 7
    assert guard_line(on.guard.as_dict()).endswith("N, set by the horizon error in 7 plans")
    off = Planner(LateModel(2.0), None, config())
    margins_off, _ = _plans(off, 12)
    assert margins_off[-1].tolist() == pytest.approx([0.0, 0.0], abs=1e-9)
    assert off.guard.as_dict()["margin_from_horizon"] == 0
    assert "horizon" not in guard_line(off.guard.as_dict())
    assert not PlannerConfig().safety.margin.lead_enabled
    assert not load_planner_config().safety.margin.lead_enabled


def test_horizon_margin_leaves_a_right_model_and_the_oracle_as_they_were() -> None:
    """An exact model: the replayed errors are 0, so Eq. M7 never sets the margin and every
    command equals the planner's without it. A model that over-predicts late in the horizon
    has m'_a = 0 too. Dynamics that roll out from their own state (``replays_history``
    False, the oracle's plant) are never replayed."""
    base = config(**{"mppi.seed": 5})
    lead = base.replace(**{"safety.margin.lead_enabled": True})
    _, plain = _plans(Planner(PlantModel(0.0), None, base), 10)
    with_m7 = Planner(PlantModel(0.0), None, lead)
    _, commands = _plans(with_m7, 10)
    assert commands == pytest.approx(plain, abs=1e-9)  # replayed errors: float rounding
    assert with_m7.guard.as_dict()["margin_from_horizon"] == 0
    high = Planner(LateModel(-3.0), None, lead)
    _plans(high, 10)
    assert high.lead_margin.value.tolist() == [0.0, 0.0]
    oracle = LateModel(2.0)
    oracle.replays_history = False
    never = Planner(oracle, None, lead)
    _plans(never, 10)
    assert all(len(e) == 0 for e in never.lead_margin.errors)


# ---------------------------------------------------------------- Eq. M8
def _loop_task(loop: ControlLoop, task: int, t0_ns: int, samples: int) -> None:
    """``samples`` samples of task ``task`` on the test plant, the blade following each
    command (the measured forces are the plant's, the model's are 2 N low on F_RX)."""
    q, u = 0.0, 0.0
    for k in range(samples):
        if k:
            q += DT * u
        fx, fz = true_forces(q, u)
        answer = loop.on_sample(Sample(t0_ns + k * 100_000_000, task, q, u, fx, fz))
        if answer is not None:
            u = answer.u_mmps


@pytest.mark.parametrize("carry", [False, True])
def test_margin_window_is_carried_into_the_next_task_only_when_asked(carry: bool) -> None:
    """Eq. M8: a model 2 N low on F_RX. Each task's first plan uses init_n (0.5 N) without
    Eq. M8; with it, the last task's window, so the next task's first plan already has the
    measured 2 N, in the control loop (a new planner per task) as in ``carry_from``."""
    cfg = config(**{"safety.margin.carry_over": carry})
    loop = ControlLoop(cfg, PlantModel(2.0), seed=0)
    _loop_task(loop, 0, 0, 31)
    assert loop.margins_n[0] == pytest.approx(2.0)
    _loop_task(loop, 1, 10_000_000_000, 1)  # the new task's first sample: its first plan
    assert loop.margins_n[0] == pytest.approx(2.0 if carry else 0.5)
    first = Planner(PlantModel(2.0), None, cfg)
    peel(first, t_max=3.0)
    second = Planner(PlantModel(2.0), None, cfg)
    second.reset()
    second.carry_from(first)
    second.carry_from(None)  # nothing to carry: unchanged
    assert second.margin.value[0] == pytest.approx(2.0 if carry else 0.5)
    assert not PlannerConfig().safety.margin.carry_over
    assert not load_planner_config().safety.margin.carry_over
