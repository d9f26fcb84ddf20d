"""`peel bench planner` as a real process: the JSON it prints, its cost study, its errors.

Small settings only (one task, one planner seed, few timing calls); no timing is asserted.
"""

from __future__ import annotations

import json
import subprocess
import sys


def _bench(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", "bench", "planner", *args],
                          capture_output=True, text=True, timeout=300)


def test_quick_benchmark_prints_both_implementations_with_paired_costs() -> None:
    out = _bench("--quick", "--tasks", "1", "--repeats", "3")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    cases = {(c["impl"], c["n"], c["h"]): c for c in report["cases"]}
    assert set(cases) == {(impl, n, h) for impl in ("peel", "pytorch_mppi")
                          for n, h in ((50, 5), (100, 5))}
    for case in cases.values():
        assert case["median_ms"] > 0 and case["p99_ms"] >= case["median_ms"]
        assert len(case["episode_costs"]) == 1 and case["outcomes"][0] in (
            "done", "safety_stop", "timeout")
    goal = report["goals"]["50x5"]
    want = cases[("peel", 50, 5)]["episode_cost"] - cases[("pytorch_mppi", 50, 5)]["episode_cost"]
    assert abs(goal["cost_diff"] - want) < 1e-3
    assert report["planner_seeds"] == [0] and report["episodes_per_case"] == 1
    assert report["planner_config"]["mppi"]["noise_correlation"] == 0.8
    ratio = cases[("peel", 50, 5)]["median_ms"] / cases[("pytorch_mppi", 50, 5)]["median_ms"]
    assert abs(goal["latency_ratio"] - ratio) < 1e-3
    floor = report["flop_floor"]
    macs = floor["macs_per_model_step"]
    assert 0 < macs["fused"] < macs["model"]  # the fused rollout skips the shift-invariant work
    case = floor["cases"]["50x5"]
    assert case["macs_per_plan"] == 50 * 5 * 5 * macs["fused"]
    assert case["floor_ms_1_threads"] > 0 and all(v > 0 for v in floor["peak_gflops"].values())


def test_cost_study_takes_base_settings_and_ad_hoc_variants() -> None:
    out = _bench("--cost-study", "--tasks", "1", "--seeds", "1", "--first-task", "3",
                 "--variants", "peel,mppi.noise_correlation=0.0+mppi.sigma_min=0.25",
                 "--set", "cost.barrier.weight=4.0")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["tasks"] == [3] and report["base_overrides"] == {"cost.barrier.weight": 4.0}
    names = [v["variant"] for v in report["variants"]]
    assert names == ["peel", "mppi.noise_correlation=0.0+mppi.sigma_min=0.25", "pytorch_mppi"]
    assert report["variants"][1]["overrides"] == {"mppi.noise_correlation": 0.0,
                                                  "mppi.sigma_min": 0.25}
    assert report["variants"][2]["diff_vs_pytorch_mppi"] == 0.0
    for v in report["variants"]:
        assert 0 <= v["near_miss"] + v["safety_stop"] <= 1
        assert v["peak_force_n"]["max"] >= v["peak_force_n"]["mean"] > 0


def test_cost_terms_report_which_critic_drives_the_plans() -> None:
    out = _bench("--cost-terms", "--tasks", "1", "--first-task", "2")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    terms = report["terms"]
    assert set(terms) == {"progress", "force_x", "force_z", "terminal", "barrier", "cost_to_go",
                          "control"}
    assert report["plans"] > 5
    assert abs(sum(t["largest_reduction_share"] for t in terms.values()) - 1.0) < 1e-3


def test_bad_settings_are_named_and_exit_non_zero() -> None:
    out = _bench("--cost-study", "--tasks", "1", "--set", "mppi.noise_correlation=2.0")
    assert out.returncode != 0
    assert "mppi.noise_correlation" in out.stderr and "Traceback" not in out.stderr
    out = _bench("--cost-study", "--tasks", "1", "--variants", "warp")
    assert out.returncode != 0 and "unknown variant 'warp'" in out.stderr
    out = _bench("--cost-study", "--tasks", "1", "--set", "novalue")
    assert out.returncode != 0 and "expected NAME=VALUE" in out.stderr
