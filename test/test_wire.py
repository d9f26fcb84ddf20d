"""The checks at the wire without ROS: counted, rate-limited drops; speed limits; model records
and reports with wrong fields; a bag whose disk fills (peel_msgs_py.wire, modelinfo, bag)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from peel_bag import bag as bagmod
from peel_bag.bagrepair import repair_bag
from peel_msgs_py.errors import PeelError
from peel_msgs_py.modelinfo import ModelRecord, UpdateReport, UpdateWait
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.wire import DropLog, SpeedLimits, first_nonfinite, trajectory_nonfinite


def test_drops_are_counted_and_logged_at_most_once_per_interval() -> None:
    now = [100.0]
    log = DropLog(every_s=5.0, clock=lambda: now[0])
    first = log.drop("/peel/cmd_vel", "twist.linear.x", "is not finite (nan)")
    assert first == ("dropped a /peel/cmd_vel message: twist.linear.x is not finite (nan) "
                     "(1 dropped so far on /peel/cmd_vel for twist.linear.x)")
    now[0] += 4.9
    assert log.drop("/peel/cmd_vel", "twist.linear.x", "is not finite (nan)") is None
    # another field, or another action on the same field, has a line of its own
    assert log.drop("/peel/wrench", "wrench.force.x", "is not finite (inf)") is not None
    assert log.drop("/peel/cmd_vel", "twist.linear.x", "= 1e+12", action="clamped") is not None
    now[0] += 0.2
    line = log.drop("/peel/cmd_vel", "twist.linear.x", "is not finite (nan)")
    assert line is not None and "(3 dropped so far" in line
    assert log.total == 5


def test_speed_limits_clamp_and_refuse_a_bad_range() -> None:
    lim = SpeedLimits()
    assert (lim.u_min_mmps, lim.u_max_mmps) == (0.0, 20.0)
    assert [lim.clamp(u) for u in (1e12, -3.0, 4.5)] == [20.0, 0.0, 4.5]
    assert lim.describe() == "0-20 mm/s"
    for lo, hi in ((5.0, 1.0), (0.0, math.nan)):
        with pytest.raises(PeelError, match="u_min <= u_max"):
            SpeedLimits(lo, hi)


def test_non_finite_fields_are_named() -> None:
    assert first_nonfinite({"fx_n": 1.0, "fz_n": math.inf}) == "fz_n"
    assert first_nonfinite({"q_mm": 0.0}) is None
    n = 3
    traj = Trajectory(t=np.arange(n) * 0.1, q=np.zeros(n), v=np.zeros(n), u=np.zeros(n),
                      fx=np.array([0.0, np.nan, 0.0]), fz=np.zeros(n), psi=np.zeros(n))
    assert trajectory_nonfinite(traj) == "fx"


@pytest.mark.parametrize("text, needle", [
    ('{"version": -1, "sha256": "a", "path": "p"}', "'version' must be an integer >= 0"),
    ('{"version": 1.5, "sha256": "a", "path": "p"}', "'version' must be an integer"),
    ('{"version": 1, "sha256": "a", "path": "p", "task": 0}', "'task' must be an integer >= 1"),
    ('{"version": 1, "sha256": 3, "path": "p"}', "'sha256' must be a string"),
])
def test_a_model_record_with_a_wrong_field_is_refused(text: str, needle: str) -> None:
    with pytest.raises(PeelError, match=needle):
        ModelRecord.from_json(text)


def test_a_report_with_a_wrong_field_is_refused_and_the_wait_takes_only_final_reports() -> None:
    with pytest.raises(PeelError, match="'task' must be an integer"):
        UpdateReport.from_json('{"producer": "/l", "task": "one", "status": "swapped"}')
    with pytest.raises(PeelError, match="'version' must be an integer >= 0"):
        UpdateReport.from_json('{"producer": "/l", "task": 1, "status": "swapped", '
                               '"version": -2}')
    wait = UpdateWait("/l")
    wait.add_record(ModelRecord(1, "abc", "m1", producer="/l", task=1))
    assert wait.outcome(1) is not None  # the planner's record of the swap ...
    assert wait.reported(1) is None  # ... is not the learner's report, which a run waits for
    wait.add_report(UpdateReport("/l", 1, "swapped", version=1))
    assert wait.reported(1).status == "swapped"


def test_a_full_disk_fails_the_bag_with_the_repair_command(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv(bagmod.FAIL_AFTER_ENV, "2000")
    path = tmp_path / "bag"
    writer = bagmod.BagWriter(path, chunk_size=256).open()
    writer.add_topic("/peel/model_info", "std_msgs/msg/String")
    payload = b"\x00\x01\x00\x00" + bytes(300)
    with pytest.raises(bagmod.BagWriteError) as err:
        for i in range(100):
            writer.write("/peel/model_info", payload, 1_000 + i)
    text = str(err.value)
    assert "No space left on device (ENOSPC)" in text
    assert text.endswith(f"repair it with: peel record --repair {path}")
    assert writer.failure is err.value
    with pytest.raises(bagmod.BagWriteError):  # a failed writer stays failed
        writer.write("/peel/model_info", payload, 5_000)
    writer.close()  # releases the file, writes nothing more
    size = writer.file_path.stat().st_size
    assert 0 < size <= 2000
    monkeypatch.delenv(bagmod.FAIL_AFTER_ENV)
    result = repair_bag(path)
    assert result.as_dict()["messages"] > 0
