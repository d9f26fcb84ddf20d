"""``peel experiment fleet``'s arithmetic and files (docs/fleet.md, "Pooled learning"): which
peels it pairs, the pooled fraction of headroom closed, the target, on hand-made runs; a fleet
run it starts is a real process whose failure it names."""

import json
import sys

import pytest
from PIL import Image

from peel_experiments import fleet_study as fs
from peel_msgs_py.errors import PeelError


def _fleet(cells):
    """A peel fleet summary: cells = {name: (seed, [(J, model_version), ...])}."""
    return {"status": 0, "tasks": len(next(iter(cells.values()))[1]),
            "cells": {n: {"seed": seed, "results": [{"task": k, "J": j, "model_version": v}
                                                     for k, (j, v) in enumerate(rs, start=1)]}
                      for n, (seed, rs) in cells.items()}}


def _alone(costs):
    """Experiment results: costs = {seed: {method: [J per task]}}."""
    return {"seeds": list(costs), "tasks": len(next(iter(costs.values()))["baseline1"]),
            "runs": {str(s): {m: {"tasks": [{"cost": c} for c in cs]} for m, cs in ms.items()}
                     for s, ms in costs.items()}}


# seed 5: cell 0 (seed 5) and cell 1 (seed 77), 2 tasks each; headroom 2 on every peel
FLEET = {5: _fleet({"/cell_0": (5, [(10.0, 0), (8.5, 1)]), "/cell_1": (77, [(10.0, 0), (8.0, 2)])})}
ALONE = [_alone({5: {"baseline1": [10.0] * 4, "oracle": [8.0] * 4,
                     "ol-mppi": [10.0, 8.5, 8.4, 8.2]}}),
         _alone({77: {"baseline1": [10.0] * 2, "oracle": [8.0] * 2, "ol-mppi": [10.0, 9.0]}})]


def _summary():
    rows = fs.peel_rows(FLEET, ALONE)
    return {"command": "peel experiment fleet ...", "cells": 2, "tasks": 2, "seeds": [5],
            "plant": {"level": 3}, **fs.analyse(*rows, cells=2, tasks=2)}


def test_rows_pair_each_fleet_peel_with_its_substrate_and_learned_peels():
    fleet_rows, alone_rows = fs.peel_rows(FLEET, ALONE)
    assert [(r["cell"], r["task"], r["learned"], r["J"]) for r in fleet_rows] == [
        ("/cell_0", 1, 0, 10.0), ("/cell_0", 2, 1, 8.5), ("/cell_1", 1, 0, 10.0),
        ("/cell_1", 2, 2, 8.0)]
    # the lone run of cell 0 has every task of the one-cell arm, a model of k - 1 peels at task k
    assert [(r["task"], r["learned"]) for r in alone_rows if r["cell"] == "/cell_0"] == [
        (1, 0), (2, 1), (3, 2), (4, 3)]
    assert all(r["J_b1"] == 10.0 and r["J_oracle"] == 8.0 for r in fleet_rows + alone_rows)


def test_closed_is_pooled_over_peels_not_a_mean_of_ratios():
    rows = [{"J": 9.0, "J_b1": 10.0, "J_oracle": 8.0},   # 1 of 2 closed
            {"J": 10.0, "J_b1": 14.0, "J_oracle": 10.0}]  # 4 of 4 closed
    c = fs.closed(rows)
    assert c["closed"] == pytest.approx(5 / 6) and c["peels"] == 2
    assert c["headroom_per_peel"] == pytest.approx(3.0)
    assert fs.closed([{"J": 5.0, "J_b1": 5.0, "J_oracle": 5.0}])["closed"] is None  # no headroom


def test_analysis_groups_by_own_task_and_by_learned_peels_and_judges_each_cell():
    s = _summary()
    assert s["fleet"]["by_task"]["2"]["closed"] == pytest.approx((1.5 + 2.0) / 4)
    assert s["fleet"]["by_learned"]["1"]["closed"] == pytest.approx(0.75)
    assert s["fleet"]["by_learned"]["2"]["closed"] == pytest.approx(1.0)
    assert s["one_cell"]["by_task"]["4"]["closed"] == pytest.approx(0.9)
    # each cell alone on its own two substrates: cell 0 0.75, cell 1 0.5 at task 2
    assert s["alone_same_cells"]["by_task"]["2"]["closed"] == pytest.approx((1.5 + 1.0) / 4)
    assert s["target"]["per_cell_closed"] == [pytest.approx(0.75), pytest.approx(1.0)]
    assert not s["target"]["met"]  # cell 0 at 75 % < 90 %
    assert s["fleet_minus_alone_J"]["2"] == {"mean": pytest.approx(-0.5), "se": pytest.approx(0.5),
                                             "n": 2, "better": 1}
    # task 1 of both cells and cell 0's task 2 planned with the lone run's models: same J
    assert s["same_model_max_abs_dJ"] == {"max": 0.0, "peels": 3}


def test_report_and_figure_are_written(tmp_path):
    s = _summary()
    md = fs.summary_markdown(s)
    assert "| 2 | 0.75 | 0.88 | 0.62 [0.50, 0.75] | -0.50 ± 0.50 (1 of 2) |" in md
    learned = md.split("| peels the model had learned |")[1].split("\n\n")[0]
    assert [row.split(" | ")[0] for row in learned.splitlines()[2:]] == ["| 0", "| 1", "| 2", "| 3"]
    assert "**not met**" in md
    png = fs.plot_closed(s, tmp_path / "headroom.png")
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size[0] > 500


def test_a_finished_fleet_run_is_reused_and_a_failed_one_is_named(tmp_path, monkeypatch):
    out = tmp_path / "fleet_s5"
    out.mkdir()
    (out / "summary.json").write_text(json.dumps(FLEET[5]))
    assert fs.run_fleet(2, 2, 5, out) == FLEET[5]  # no process started: same cells and tasks
    fails = [sys.executable, "-c", "import sys; print('cell /cell_1 died'); sys.exit(1)"]
    monkeypatch.setattr(fs, "fleet_command", lambda *a: fails)
    with pytest.raises(PeelError, match=r"exited 1; its output: .*fleet_s5\.log"):
        fs.run_fleet(3, 2, 5, out)  # three cells asked for: the two-cell run is not reused
    assert "cell /cell_1 died" in (tmp_path / "fleet_s5.log").read_text()


def test_the_interval_resamples_substrate_sequences_and_brackets_the_pooled_fraction():
    rows = [{"seed": 1, "cell": c, "task": 2, "J": j, "J_b1": 10.0, "J_oracle": 8.0}
            for c, j in (("/cell_0", 9.0), ("/cell_1", 8.0), ("/cell_2", 8.5))]
    lo, hi = fs.seed_interval(rows)
    assert 0.5 <= lo <= fs.closed(rows)["closed"] <= hi <= 1.0  # per sequence 0.5, 1.0, 0.75
    assert fs.seed_interval(rows[:1]) is None  # one sequence: no interval
    assert fs.seed_interval(rows) == fs.seed_interval(rows)  # seeded
