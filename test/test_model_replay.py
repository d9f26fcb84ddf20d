"""Experience replay of trajectory slices (3.3.1, Fig. 6) and model windows (Eq. 1-2)."""

import numpy as np
import pytest

from model_learner_node.replay import ReplayPool
from peel_model.windows import last_history, stack_windows, trajectory_windows
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory


def tagged(tid: int, n: int) -> Trajectory:
    """q encodes (trajectory id, sample index) so a slice tells where each row came from."""
    k = np.arange(n, dtype=float)
    return Trajectory(t=k * 0.1, q=tid * 1000 + k, v=k + 0.5, u=k, fx=-k, fz=k * 2, psi=k * 0.01,
                      outcome="done")


@pytest.mark.parametrize("pad_front", [0, 9])
@pytest.mark.parametrize("length", [2, 11, 25])
def test_slices_never_cross_trajectory_ends(pad_front, length):
    lengths = [5, 11, 12, 30, 3, 24, 40]
    pool = ReplayPool([tagged(i, n) for i, n in enumerate(lengths)], pad_front=pad_front)
    batch = pool.sample_slices(2000, length, np.random.default_rng(7))
    assert batch.states.shape == (2000, length, 4)
    ids = batch.states[:, :, 0] // 1000
    idx = batch.states[:, :, 0] % 1000
    assert (ids == ids[:, :1]).all(), "a slice joined two trajectories"
    np.testing.assert_array_equal(ids[:, 0], batch.traj_index)
    for row, tid, start in zip(idx, batch.traj_index, batch.start, strict=True):
        assert lengths[tid] + pad_front >= length
        assert start + length <= lengths[tid] + pad_front, "a slice ran past the end"
        # real rows are consecutive; padded rows (only at the front) repeat sample 0
        expected = np.clip(np.arange(start, start + length) - pad_front, 0, None)
        np.testing.assert_array_equal(row, expected)
    # padded rows stand still (v = 0); real rows keep their velocity
    padded = (np.arange(length)[None, :] + batch.start[:, None]) < pad_front
    np.testing.assert_array_equal(batch.states[:, :, 1][padded], 0.0)
    np.testing.assert_array_equal(batch.states[:, :, 1][~padded], idx[~padded] + 0.5)
    # every trajectory long enough is used, none too short is
    used = set(batch.traj_index.tolist())
    assert used == {i for i, n in enumerate(lengths) if n + pad_front >= length}


def test_sampling_is_seeded_and_psi_follows_states():
    pool = ReplayPool([tagged(i, 20 + i) for i in range(5)])
    a = pool.sample_slices(50, 6, np.random.default_rng(3))
    b = pool.sample_slices(50, 6, np.random.default_rng(3))
    np.testing.assert_array_equal(a.states, b.states)
    np.testing.assert_allclose(a.psi, (a.states[:, :, 0] % 1000) * 0.01)


def test_no_long_enough_trajectory_is_an_error():
    pool = ReplayPool([tagged(0, 4)])
    with pytest.raises(PeelError, match="at least 5 samples"):
        pool.sample_slices(1, 5, np.random.default_rng(0))


def test_capacity_drops_oldest():
    pool = ReplayPool([tagged(i, 10) for i in range(5)], capacity=3)
    assert len(pool) == 3
    assert [int(t.q[0] // 1000) for t in pool.trajectories] == [2, 3, 4]


def test_windows_from_slices_are_one_step_triples():
    pool = ReplayPool([tagged(3, 30)])
    batch = pool.sample_slices(4, 14, np.random.default_rng(1))
    win = batch.windows(10)
    assert len(win) == 4 * 4
    assert win.hist.shape == (16, 10, 4)
    k = win.hist[:, -1, 0] % 1000  # last history sample index
    np.testing.assert_array_equal(win.v_next, k + 1 + 0.5)
    np.testing.assert_array_equal(win.f_next[:, 0], -(k + 1))
    np.testing.assert_array_equal(win.f_next[:, 1], 2 * (k + 1))
    np.testing.assert_allclose(win.psi_next, (k + 1) * 0.01)
    np.testing.assert_array_equal(np.diff(win.hist[:, :, 0], axis=1), 1.0)


def test_trajectory_windows_cover_every_step_with_front_padding():
    traj = tagged(1, 15)
    win = trajectory_windows(traj, 10)
    assert len(win) == 14  # k = 0..13 -> F_1..F_14
    np.testing.assert_array_equal(win.f_next[:, 0], -np.arange(1, 15))
    np.testing.assert_array_equal(win.hist[0, :, 0], np.full(10, 1000.0))
    np.testing.assert_array_equal(win.hist[0, :-1, 1], 0.0)  # padding at rest
    np.testing.assert_array_equal(win.hist[0], last_history(traj.slice(0, 1), 10))
    np.testing.assert_array_equal(win.hist[-1], last_history(traj.slice(0, 14), 10))
    both = stack_windows([traj, tagged(2, 3)], 10)
    assert len(both) == 14 + 2
