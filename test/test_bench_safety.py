"""``peel bench safety``: prewarnings, peels over 18 N, J, T_cpl and peak force per level and
arm as JSON; and ``peel experiment``'s trajectories carry the planner's guard."""

from __future__ import annotations

import json
import subprocess
import sys

from peel_experiments.bench_safety import summary, wilson


def _bench(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", "bench", "safety", *args],
                          capture_output=True, text=True, timeout=600)


def test_summary_counts_stops_peaks_and_the_guard() -> None:
    runs = [{"J": 10.0, "t": 5.0, "out": "done", "peak": 17.0, "reduced": 1, "fallbacks": 0,
             "margin_mean": 1.0},
            {"J": 20.0, "t": 3.0, "out": "safety_stop", "peak": 20.4, "reduced": 0,
             "fallbacks": 2, "margin_mean": 2.0},
            {"J": 12.0, "t": 6.0, "out": "done", "peak": 18.0, "reduced": 0, "fallbacks": 0,
             "margin_mean": 0.0},
            {"J": 14.0, "t": 7.0, "out": "done", "peak": 16.0, "reduced": 3, "fallbacks": 1,
             "margin_mean": 1.0}]
    s = summary(runs, [0, 1], 18.0)
    assert (s["peels"], s["prewarnings"], s["over_18n"], s["done"]) == (4, 1, 2, 3)
    assert s["share_over_18n"] == 0.5 and s["J"]["mean"] == 14.0
    assert s["J"]["ci95"][0] < 14.0 < s["J"]["ci95"][1]
    assert s["peak_n"]["max"] == 20.4
    assert s["by_planner_seed"]["0"] == {"prewarnings": 1, "over_18n": 1, "J": 15.0,
                                         "t_cpl_s": 4.0}
    assert s["by_planner_seed"]["1"]["over_18n"] == 1
    assert (s["commands_reduced"], s["fallbacks"]) == (4, 3)
    assert s["prewarning_rate"] == {"rate": 0.25, "ci95_wilson": wilson(1, 4)}


def test_wilson_interval_of_a_rate() -> None:
    """The 95 % Wilson score interval: 0 of 300 -> [0, 1.26 %] (the rule of three's ~1 %),
    5 of 100 -> [2.15 %, 11.2 %] (textbook values)."""
    assert wilson(0, 300) == [0.0, 0.01264]
    lo, hi = wilson(5, 100)
    assert abs(lo - 0.02154) < 1e-4 and abs(hi - 0.11175) < 1e-4
    assert wilson(0, 0) == [0.0, 1.0]


def test_bench_safety_prints_every_level_and_arm_as_json() -> None:
    res = _bench("--levels", "sim,1", "--sequences", "drift", "--tasks", "1", "--seed", "5",
                 "--latency-repeats", "2")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert [(c["level"], c["sequence"]) for c in out["cells"]] == [("sim", None), ("1", "drift")]
    for cell in out["cells"]:
        assert set(cell["arms"]) == {"peel", "peel_unguarded", "pytorch_mppi"}
        for arm in cell["arms"].values():
            assert arm["peels"] == 1 and arm["prewarnings"] + arm["done"] <= 1
            assert set(arm["J"]) == {"mean", "ci95"} and arm["peak_n"]["max"] > 0.0
        assert cell["arms"]["pytorch_mppi"]["fallbacks"] == 0
        assert cell["arms"]["peel"]["margin_mean_n"] > 0.0  # the shipped planner is guarded
        assert cell["arms"]["peel_unguarded"]["margin_mean_n"] == 0.0
    lat = out["latency"]["arms"]
    assert set(lat) == {"peel", "peel_unguarded", "pytorch_mppi"} and out["latency"]["n"] == 50
    assert lat["pytorch_mppi"]["ratio_to_pytorch_mppi"] == 1.0 and lat["peel"]["median_ms"] > 0


def test_bench_safety_refuses_bad_arguments() -> None:
    res = _bench("--levels", "sim,7")
    assert res.returncode != 0 and "--levels" in res.stderr
    res = _bench("--arms", "peel,oracle")
    assert res.returncode != 0 and "unknown arm" in res.stderr


def test_experiment_trajectory_meta_carries_the_planner_guard() -> None:
    from peel_experiments.experiment import Setup, planner_params, run_job
    from peel_model.checkpoint import shipped_checkpoint

    setup = Setup(checkpoint=str(shipped_checkpoint()), tasks=1, planner_params=planner_params(),
                  save_model=False, plant_level=1)
    rec = run_job("baseline1", 0, setup)["tasks"][0]
    guard = rec["planner_guard"]
    assert guard["plans"] >= 5 and len(guard["margin_max_n"]) == 2
    assert set(guard) == {"plans", "commands_reduced", "reduced_max_mmps", "fallbacks",
                          "all_samples_unsafe", "margin_last_n", "margin_mean_n",
                          "margin_max_n"}
