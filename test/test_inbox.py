"""Reports taken from the wire: the same refusals, for the same words, in every node."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from std_msgs.msg import String

from peel_msgs_py import inbox
from peel_msgs_py.modelinfo import SWAPPED, ModelRecord, UpdateReport
from peel_msgs_py.ros.messages import trajectory_msg
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.wire import DropLog


def _traj(n: int = 20) -> Trajectory:
    t = np.arange(n) * 0.1
    return Trajectory(t=t, q=np.linspace(0.0, 5.0, n), v=np.full(n, 2.5), u=np.full(n, 2.5),
                      fx=np.full(n, 4.0), fz=np.full(n, -1.0), psi=np.zeros(n), outcome="done")


def test_each_report_decodes_back_to_what_was_sent() -> None:
    traj = inbox.trajectory(trajectory_msg(_traj()))
    np.testing.assert_array_equal(traj.fx, _traj().fx)
    rec = ModelRecord(3, "ab" * 32, "/m.safetensors")
    assert inbox.model_record(String(data=rec.to_json())) == rec
    rep = UpdateReport("model_learner", 3, SWAPPED, "ok")
    assert inbox.update_report(String(data=rep.to_json())) == rep


@pytest.mark.parametrize("decode, msg, name, why", [
    (inbox.trajectory, SimpleNamespace(layout=SimpleNamespace(dim=[], data_offset=0), data=[]),
     "layout", "does not decode"),
    (inbox.model_record, String(data="{not json"), "data", "is not a model record"),
    (inbox.update_report, String(data='{"version": 1}'), "data", "is not an update report"),
])
def test_a_message_that_does_not_decode_is_refused_naming_its_field(decode, msg, name,
                                                                    why) -> None:
    with pytest.raises(inbox.Refused) as err:
        decode(msg)
    assert (err.value.name, err.value.why.split(":")[0]) == (name, why)


def test_a_non_finite_array_is_refused_by_name() -> None:
    bad = _traj()
    bad.q[4] = np.nan
    with pytest.raises(inbox.Refused) as err:
        inbox.trajectory(trajectory_msg(bad))
    assert (err.value.name, err.value.why) == ("'q'", "holds non-finite values")


def test_take_counts_every_refusal_and_logs_the_first_of_a_kind() -> None:
    now = [0.0]
    drops, lines = DropLog(every_s=5.0, clock=lambda: now[0]), []
    bad = String(data="[]")
    for step in (0.0, 1.0, 6.0):
        now[0] = step
        assert inbox.take(drops, "/peel/model_info", inbox.model_record, bad, lines.append) is None
    assert drops.counts == {("/peel/model_info", "data", "dropped"): 3}
    assert len(lines) == 2 and "(3 dropped so far" in lines[1], lines
    good = String(data=ModelRecord(1, "cd" * 32, "/m.safetensors").to_json())
    assert inbox.take(drops, "/peel/model_info", inbox.model_record, good, lines.append).version == 1
