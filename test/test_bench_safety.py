"""``peel bench safety``: prewarnings, peels over 18 N, J, T_cpl and peak force per level and
arm as JSON; and ``peel experiment``'s trajectories carry the planner's guard."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

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


@pytest.mark.slow
def test_the_oracle_tells_an_avoidable_stop_from_an_unpeelable_substrate() -> None:
    """Level 1, drift, seed 8, task 18: the force passes 20 N under the oracle and at every
    constant speed, so the unguarded planner's stop there is not avoidable; on a simulator
    substrate the oracle finishes, a stop counts as avoidable."""
    from peel_experiments.bench_safety import peels_of
    from peel_experiments.stops import oracle_on_stops
    from peel_planner_node.config import load_planner_config
    from peel_sim_node.config import load_sim_config

    res = _bench("--levels", "1", "--sequences", "drift", "--tasks", "18", "--seed", "8",
                 "--arms", "peel_unguarded", "--latency-repeats", "0", "--oracle-on-stops")
    assert res.returncode == 0, res.stderr
    cell = json.loads(res.stdout)["cells"][0]
    arm = cell["arms"]["peel_unguarded"]
    assert arm["prewarnings"] >= 1 and arm["prewarnings_avoidable"] == 0
    [check] = cell["oracle_on_stops"]
    assert (check["task"], check["out"], check["peelable"]) == (17, "safety_stop", False)
    assert set(check["constant"]) == {"0.5", "1", "2", "4", "8"}
    assert set(check["constant"].values()) == {"safety_stop"}
    base = load_planner_config()
    env, peels = peels_of("sim", "stationary", 5, 1, load_sim_config())
    try:
        checked, avoidable = oracle_on_stops(env, peels, {"a": ["safety_stop"], "b": ["done"]},
                                             base, 0)
    finally:
        env.close()
    assert [(c["task"], c["out"], c["peelable"]) for c in checked] == [(0, "done", True)]
    assert avoidable == {"a": 1, "b": 0}


@pytest.mark.slow
def test_the_stops_of_an_experiment_are_replayed_on_their_substrates(tmp_path: Path) -> None:
    """``--experiments``: a ``peel experiment`` folder's peels (Baseline 1: the model that
    never learns) on the same drifting level-1 substrates; the stop at task 18 is on the
    substrate that nothing peels, so none of its stops there counts as avoidable."""
    out = tmp_path / "exp"
    run = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "experiment", "--plant", "1",
                          "--sequence", "drift", "--tasks", "18", "--seed", "8", "--methods",
                          "baseline1", "--no-oracle", "--no-save-model", "--out", str(out)],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    res = _bench("--experiments", str(out))
    assert res.returncode == 0, res.stderr
    rep = json.loads(res.stdout)
    [cell] = rep["cells"]
    assert (cell["level"], cell["sequence"], cell["seeds"]) == ("1", "drift", [8])
    b1 = cell["methods"]["baseline1"]
    last = [s for s in b1["stops"] if s["task"] == 18]
    assert b1["peels"] == 18 and [(s["seed"], s["out"], s["peelable"]) for s in last] == [
        (8, "safety_stop", False)]
    assert b1["prewarnings"] == len(b1["stops"]) >= 1
    assert b1["prewarnings_avoidable"] == sum(s["peelable"] for s in b1["stops"])
    # Baseline 1 never swaps its model, and no other method peeled these substrates
    assert all(s["model_version"] == 0 and s["others"] == {} and s["peak_n"] >= 20.0
               for s in b1["stops"]), b1["stops"]
    assert rep["total"]["baseline1"]["prewarnings"] == b1["prewarnings"]
    bad = _bench("--experiments", str(tmp_path / "nothing"))
    assert bad.returncode != 0 and "results.json does not exist" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1


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
                          "all_samples_unsafe", "commands_slowed", "margin_from_horizon",
                          "margin_last_n", "margin_mean_n", "margin_max_n"}


def test_a_stop_names_its_model_and_how_the_other_methods_peeled_that_substrate() -> None:
    from peel_experiments.stops import others, stop_record

    def rec(task: int, outcome: str, fx: float, version: int) -> dict[str, object]:
        return {"task": task, "outcome": outcome, "max_abs_fx": fx, "max_abs_fz": 9.0,
                "t_cpl": 3.4, "model_version": version,
                "planner_guard": {"fallbacks": 2, "margin_max_n": [2.1, 1.1]}}

    res = {"runs": {"7": {"ol-mppi": {"tasks": [rec(1, "done", 15.0, 0), rec(2, "safety_stop", 20.4, 1)]},
                          "baseline1": {"tasks": [rec(1, "done", 14.0, 0), rec(2, "done", 17.5, 0)]}}}}
    same = others(res, 7, 2)
    assert {m: r["max_abs_fx"] for m, r in same.items()} == {"ol-mppi": 20.4, "baseline1": 17.5}
    got = stop_record(same["ol-mppi"], {m: r for m, r in same.items() if m != "ol-mppi"})
    assert got == {"model_version": 1, "t_stop_s": 3.4, "peak_n": 20.4, "fallbacks": 2,
                   "margin_max_n": [2.1, 1.1],
                   "others": {"baseline1": {"outcome": "done", "peak_n": 17.5}}}
