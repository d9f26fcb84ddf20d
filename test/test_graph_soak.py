"""``peel soak``: consecutive peels through ``peel graph`` with every node's memory.

The memory probe is checked on a real process tree whose processes hold known amounts of
memory; the command end to end with two short peels on the simulator (the 100-peel soak on the
plant is a command to run, not part of the suite).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import matplotlib.image as mpimg
import pytest
import torch
from graph_helpers import ALONE, FAST, SIM_TASKS, node_env, override_yaml

from peel_experiments.soak import Watch, _markdown, build_report, memory_summary, sample_tree

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

# A "launcher" that starts two processes run as console scripts named like nodes; each holds
# the given number of MB, then all wait to be killed.
HOLD = "import sys, time\nb = b'x' * (int(sys.argv[1]) << 20)\nprint('held', flush=True)\ntime.sleep(600)\n"
LAUNCHER = textwrap.dedent("""
    import subprocess, sys, time
    kids = [subprocess.Popen([sys.executable, path, mb], stdout=subprocess.PIPE, text=True)
            for path, mb in zip(sys.argv[1::2], sys.argv[2::2])]
    for k in kids:
        k.stdout.readline()
    print('ready', flush=True)
    time.sleep(600)
""")


def test_sample_tree_names_each_node_and_reads_its_rss(tmp_path: Path) -> None:
    for name in ("peel_sim_node", "model_learner_node"):
        (tmp_path / name).write_text(HOLD)
    proc = subprocess.Popen([sys.executable, "-c", LAUNCHER, str(tmp_path / "peel_sim_node"),
                             "60", str(tmp_path / "model_learner_node"), "150"],
                            stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        rss = sample_tree(proc.pid)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the launcher and the two holders it started
        proc.wait(timeout=30)
        proc.stdout.close()
    assert set(rss) == {"peel_graph", "peel_sim_node", "model_learner_node"}
    assert 60 <= rss["peel_sim_node"] < 120
    assert 150 <= rss["model_learner_node"] < 210
    assert rss["peel_graph"] < 60


def test_memory_summary_flat_growth_and_slope() -> None:
    tasks = [{"task": k, "rss_mb": {"learner": 300.0 + min(k, 5) * 10.0 + (k > 10) * 2.0 * (k - 10),
                                   "sim": 80.0}} for k in range(1, 31)]
    mem = memory_summary(tasks, warmup=10, max_growth_mb=25.0)
    assert mem["sim"]["flat"] is True and mem["sim"]["growth_after_warmup_mb"] == 0.0
    learner = mem["learner"]
    assert learner["rss_mb_first"] == 310.0 and learner["rss_mb_at_warmup"] == 350.0
    assert learner["growth_after_warmup_mb"] == 40.0 and learner["flat"] is False
    assert learner["slope_mb_per_task"] == pytest.approx(2.0, abs=0.01)
    assert (mem["sim"]["verdict"], learner["verdict"]) == ("flat", "grew")
    short = memory_summary(tasks[:5], warmup=10, max_growth_mb=25.0)
    assert short["learner"]["flat"] is None  # too few tasks to say
    assert short["learner"]["verdict"] == "too_few_tasks"


def test_a_node_with_no_sample_after_the_warmup_is_named_not_judged() -> None:
    """The last task's line can be read after the graph began stopping its nodes: a node seen
    only before the warm-up ends has no growth to judge, and the report says so."""
    tasks = [{"task": 1, "rss_mb": {"peel_graph": 90.0, "learner": 300.0}},
             {"task": 2, "rss_mb": {"peel_graph": 91.0}}]
    mem = memory_summary(tasks, warmup=1, max_growth_mb=25.0)
    assert mem["learner"]["verdict"] == "no_sample_after_warmup"
    assert mem["learner"]["flat"] is None and mem["learner"]["growth_after_warmup_mb"] is None
    assert mem["learner"]["rss_mb_last"] == 300.0
    assert mem["peel_graph"]["verdict"] == "flat" and mem["peel_graph"]["flat"] is True
    args = SimpleNamespace(argv=[], tasks=2, plant="sim", seed=0, params=None, warmup=1,
                           max_growth_mb=25.0)
    watch = Watch(tasks=[{**t, "outcome": "done", "t_s": 0.0} for t in tasks])
    rep = build_report(args, 0, watch, None, 1.0)
    assert rep["memory_flat"] is None and rep["nodes"]["learner"]["verdict"] == "no_sample_after_warmup"
    assert "| learner | 300.0 | - | 300.0 | 300.0 | - | - | no_sample_after_warmup |" in _markdown(rep)


def _override(init: Path) -> str:
    return override_yaml(SIM_TASKS, FAST, ALONE, {
        "peel_planner_node": {"model": {"path": init}},
        "model_learner_node": {"node": {"init_model": init}},
        "peel_bringup": {"graph": {"final_model_wait_s": 120.0}},
    })


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_soak_two_peels_reports_every_node(tmp_path: Path, ros_domain: str) -> None:
    from peel_model.checkpoint import save_checkpoint
    from peel_model.config import ModelConfig
    from peel_model.predictor import ForcePredictor

    torch.manual_seed(0)
    init = save_checkpoint(tmp_path / "init.safetensors", ForcePredictor(ModelConfig()))
    override = tmp_path / "override.yaml"
    override.write_text(_override(init))
    out = tmp_path / "soak"
    env = node_env()
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "soak", "--tasks", "2",
                           "--warmup", "1", "--plant", "sim", "--params", str(override),
                           "--out", str(out), "--interval", "1"],
                          capture_output=True, text=True, timeout=540, env=env)
    assert proc.returncode in (0, 1), proc.stderr[-3000:]  # 1 only if a node's memory grew
    printed = json.loads(proc.stdout)
    rep = json.loads((out / "soak.json").read_text())
    summary = json.loads((out / "graph" / "summary.json").read_text())  # the graph's own
    assert rep["graph_exit_status"] == 0 and rep["tasks_finished"] == 2
    assert [t["task"] for t in rep["per_task"]] == [1, 2]
    assert [t["outcome"] for t in rep["per_task"]] == [r["outcome"] for r in summary["results"]]
    assert rep["safety_stops"] == sum(r["outcome"] == "safety_stop" for r in summary["results"])
    every = {"peel_graph", "peel_sim_node", "peel_planner_node", "model_learner_node"}
    # the periodic samples (every --interval s while the graph runs) see every node; a task
    # line may be read after the graph has begun stopping its nodes on a loaded machine, so the
    # per-task samples hold a subset of them
    assert set().union(*(s["rss_mb"] for s in rep["samples"])) == every
    for t in rep["per_task"]:
        assert set(t["rss_mb"]) <= every and "peel_graph" in t["rss_mb"]
        assert all(mb > 30 for mb in t["rss_mb"].values())  # python + numpy at least
    assert len(rep["samples"]) >= 2 and rep["samples"][-1]["t_s"] <= time.monotonic() - t0
    for name, node in rep["nodes"].items():
        if node["verdict"] in ("flat", "grew"):
            assert node["flat"] == (node["growth_after_warmup_mb"] <= 25.0), name
        else:  # the node had stopped before task 2's line was read
            assert node["verdict"] == "no_sample_after_warmup" and node["flat"] is None, name
            assert f"memory of {name} not judged" in proc.stderr
        assert printed["nodes"][name]["rss_mb_last"] == node["rss_mb_last"]
    assert "peel_graph" in rep["nodes"] and rep["nodes"]["peel_graph"]["verdict"] != "no_sample_after_warmup"
    grew = rep["memory_flat"] is False
    assert proc.returncode == (1 if grew or rep["safety_stops"] else 0)
    md = (out / "soak.md").read_text()
    assert "| peel_planner_node |" in md and f"safety stops: {rep['safety_stops']}" in md
    assert mpimg.imread(out / "soak_rss.png").ndim == 3
