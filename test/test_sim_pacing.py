"""``node.real_time_factor`` (peel_sim_node.pacing.Pace): a task's samples held back until
their wall time, none held at factor 0, and the same samples in the same order at any factor."""

from __future__ import annotations

import pytest

from peel_msgs_py.task import Sample
from peel_sim_node.pacing import Pace


def _period(start_s: float) -> list[Sample]:
    """The five samples of one control period after the control instant at ``start_s``."""
    return [Sample(round((start_s + 0.1 * k) * 1e9), 0, 0.1 * k, 1.0, 1.0, 0.0)
            for k in range(1, 6)]


def test_samples_are_held_until_their_wall_time_at_real_time() -> None:
    pace = Pace(1.0)
    pace.start(Sample(0, 0, 0.0, 0.0, 0.0, 0.0), now=100.0)
    pace.hold(_period(0.0))
    assert pace.release(100.05) == []  # the first is due 0.1 s after the task's first sample
    assert [s.stamp_ns for s in pace.release(100.25)] == [100_000_000, 200_000_000]
    assert len(pace.waiting) == 3
    assert len(pace.release(100.5)) == 3 and not pace.waiting


def test_a_factor_of_four_runs_four_times_real_time() -> None:
    pace = Pace(4.0)
    pace.start(Sample(0, 0, 0.0, 0.0, 0.0, 0.0), now=0.0)
    pace.hold(_period(0.0))
    assert len(pace.release(0.124)) == 4 and len(pace.release(0.125)) == 1


def test_factor_zero_holds_nothing_back_and_keeps_the_order() -> None:
    pace = Pace(0.0)
    pace.start(Sample(0, 0, 0.0, 0.0, 0.0, 0.0), now=50.0)
    period = _period(0.0)
    pace.hold(period)
    assert pace.release(0.0) == period


def test_a_negative_factor_is_refused() -> None:
    with pytest.raises(ValueError, match="real-time factor must be >= 0"):
        Pace(-1.0)
