"""Eq. M6, the bridges' slowdown zone on the measured force at the sensor rate
(:mod:`peel_bridge.slowdown`): the formula, its parameters on both bridges, and what it does on
the plant under a command that trips the prewarning without it."""

from __future__ import annotations

import numpy as np
import pytest

from peel_bridge.slowdown import SlowdownParams, SlowdownZone, slowdown_line
from peel_experiments.experiment import substrates
from peel_msgs_py.errors import ParameterError
from peel_nachi_bridge.config import load_config
from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv
from peel_sim_node.episode import run_episode


def zone(enabled: bool = True) -> SlowdownZone:
    return SlowdownParams(enabled, 17.0, 0.5).zone(20.0)


def test_the_speed_follows_eq_m6_and_never_rises_above_the_command() -> None:
    z = zone()
    for f, u_cmd, want in [(10.0, 4.0, 4.0), (16.99, 4.0, 4.0), (17.0, 4.0, 4.0),
                           (18.5, 4.0, 2.0), (-18.5, 4.0, 2.0), (19.7, 4.0, 0.5),
                           (25.0, 4.0, 0.5), (18.5, 0.3, 0.3), (18.5, 0.8, 0.5)]:
        z.measured(f, 1.0)
        assert z.speed(u_cmd) == pytest.approx(want), (f, u_cmd)
    z.measured(2.0, -18.5)  # |F_RZ| counts as |F_RX| does
    assert z.limit(6.0) == pytest.approx(3.0)
    stats = z.as_dict()
    assert stats["samples"] == 9 and stats["samples_slowed"] == 5
    assert stats["min_scale"] == pytest.approx(0.125)
    line = slowdown_line(3, stats)
    assert line is not None and "task 3" in line and "5 of 9 samples" in line
    z.reset()
    assert z.as_dict()["samples_slowed"] == 0 and slowdown_line(1, z.as_dict()) is None
    off = zone(enabled=False)
    off.measured(19.9, 0.0)
    assert off.speed(8.0) == 8.0 and off.as_dict()["samples_slowed"] == 0


def test_with_a_lead_each_axis_is_carried_ahead_at_its_last_rise() -> None:
    """L = 2: F_k = max_a(F_a,k + 2 max(0, F_a,k - F_a,k-1)); a task's first sample has no rise,
    a falling force is not carried down, and reset() forgets the previous sample."""
    z = SlowdownParams(True, 17.0, 0.5, lead_samples=2).zone(20.0)
    z.measured(16.0, 0.0)                       # first sample: F_k = 16, below f_s
    assert z.speed(4.0) == 4.0
    z.measured(16.5, 3.0)                       # RX rose 0.5: F_k = 17.5, s = 5/6
    assert z.speed(4.0) == pytest.approx(4.0 * 2.5 / 3.0)
    z.measured(15.0, 6.0)                       # RX fell (not carried down), RZ rose 3: F_k = 12
    assert z.speed(4.0) == 4.0
    z.measured(18.0, 6.0)                       # RX rose 3: F_k = 24, the floor
    assert z.speed(4.0) == 0.5
    stats = z.as_dict()
    assert stats["lead_samples"] == 2 and stats["samples_slowed"] == 2
    assert "from 17 N, 2 ahead" in (slowdown_line(4, stats) or "")
    z.reset()
    z.measured(16.9, 0.0)                       # no previous sample after reset: no rise
    assert z.speed(4.0) == 4.0
    assert load_sim_config({"safety.slowdown.lead_samples": 1}).slowdown_zone().lead_samples == 1
    assert load_config({"safety.slowdown.lead_samples": 3}).safety.slowdown.lead_samples == 3
    with pytest.raises(ParameterError, match=r"safety\.slowdown\.lead_samples"):
        load_sim_config({"safety.slowdown.lead_samples": 6})


def test_both_bridges_ship_it_off_and_refuse_a_start_at_or_above_the_prewarning() -> None:
    """Enabled, f_s must lie below the prewarning; disabled, the prewarning may go below f_s."""
    assert load_sim_config().slowdown_zone().enabled is False
    assert load_config().safety.slowdown == SlowdownParams()
    on = {"safety.slowdown.enabled": True}
    with pytest.raises(ParameterError, match=r"'safety\.slowdown\.start_n' = 20\.0 must be below"):
        load_sim_config({**on, "safety.slowdown.start_n": 20.0})
    with pytest.raises(ParameterError, match=r"'safety\.slowdown\.start_n' = 21\.0 must be below"):
        load_config({**on, "safety.slowdown.start_n": 21.0})
    assert load_sim_config({"safety.slowdown.start_n": 20.0}).slowdown_zone().enabled is False
    assert load_config({"safety.f_prewarn_n": 15.0}).safety.slowdown.start_n == 17.0
    with pytest.raises(ParameterError, match=r"safety\.slowdown\.floor_mmps"):
        load_sim_config({"safety.slowdown.floor_mmps": -1.0})


def _peels(enabled: bool, u: float = 6.0) -> list:
    cfg = load_sim_config({"safety.slowdown.enabled": enabled})
    subs = substrates(cfg, 7, 6, 0, 1, "stationary")
    with PeelEnv(cfg, source="plant", seed=0, params=subs[0], level=1) as env:
        return [run_episode(env, lambda h: u, seed=k, params=p) for k, p in enumerate(subs)]


def test_on_the_plant_the_zone_finishes_peels_that_a_fixed_6_mmps_stops() -> None:
    """Level 1, seed 7, the blade held at 6 mm/s: without the zone most peels trip the 20 N
    prewarning; with it none does, and every sample's speed is Eq. M6 of the sample before."""
    off, on = _peels(False), _peels(True)
    assert sum(t.outcome == "safety_stop" for t in off) >= 3
    assert [t.outcome for t in on] == ["done"] * len(on)
    assert all(t.meta["slowdown"]["samples_slowed"] == 0 for t in off)
    assert sum(t.meta["slowdown"]["samples_slowed"] for t in on) >= len(on)
    for t in on:
        f = np.maximum(np.abs(t.fx), np.abs(t.fz))[:-1]
        s = np.clip((20.0 - f) / 3.0, 0.0, 1.0)
        want = np.where(f >= 17.0, np.minimum(6.0, np.maximum(0.5, s * 6.0)), 6.0)
        np.testing.assert_allclose(t.u[:-1], want, atol=1e-9)
        assert float(np.max(f)) < 20.0
