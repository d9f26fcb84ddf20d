"""Bad input to every ``peel`` command: one line naming the problem, exit 2, before any work.

Each case is what a careful user or a faulty machine gives a command: an output location that
cannot be written (``/proc``, an existing file, a folder holding other files or an earlier run),
a device torch does not have, NaN / infinity / out-of-range numbers, a dataset with a truncated
shard, a parameter file that is not UTF-8. The cheap commands run in-process through
``peel_bringup.cli.main`` (the same top-level handler the ``peel`` script runs); the ones that
start processes or ROS (graph, demo, record) and the ``python -m`` entry points run as real
processes. After each refusal, no output folder or file the command would have created exists.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from peel_bringup.cli import main as peel_main
from peel_model.checkpoint import load_checkpoint, save_checkpoint, shipped_checkpoint
from peel_sim_node.config import load_sim_config
from peel_sim_node.dataset import generate_dataset


@pytest.fixture(autouse=True)
def _torch_threads():
    """In-process commands may set torch's thread count: restore it for the tests after."""
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, Path]:
    """A tiny complete dataset, a copy with a truncated test shard, a non-UTF-8 parameter
    file, a plain file, a folder of someone else's files, a checkpoint and one whose outputs
    are not finite (the shipped weights times 1e30: finite tensors, infinite forces)."""
    root = tmp_path_factory.mktemp("cli")
    ds = root / "ds"
    generate_dataset(load_sim_config(), ds, param_sets=3, per_set=1, seed=0, progress=False)
    bad = root / "ds_truncated"
    shutil.copytree(ds, bad)
    shard = next((bad / "test").glob("set_*.parquet"))
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])
    (root / "latin1.yaml").write_bytes("peel_sim_node:\n  ros__parameters: {}\n# \xb5m\n"
                                       .encode("latin-1"))
    (root / "plain.txt").write_text("not a folder")
    (root / "empty.yaml").write_text("# a parameter file that sets nothing\n")
    (root / "params_dir").mkdir()
    (root / "foreign").mkdir()
    (root / "foreign" / "thesis.tex").write_text("someone else's work")
    pred = load_checkpoint(shipped_checkpoint())
    save_checkpoint(root / "model.safetensors", pred)
    with torch.no_grad():
        for p in pred.parameters():
            p.mul_(1e30)
    save_checkpoint(root / "huge.safetensors", pred)
    return {"root": root, "ds": ds, "bad": bad, "latin1": root / "latin1.yaml",
            "file": root / "plain.txt", "foreign": root / "foreign",
            "empty": root / "empty.yaml", "params_dir": root / "params_dir",
            "model": root / "model.safetensors", "huge": root / "huge.safetensors"}


def _argv(template: list[str], env: dict[str, Path], tmp: Path) -> list[str]:
    """``{ds}``-style placeholders -> paths of the fixture; ``{tmp}`` -> this test's folder."""
    names = {k: str(v) for k, v in env.items()} | {"tmp": str(tmp)}
    return [a.format(**names) for a in template]


def _one_line(err: str, prog: str, needle: str) -> None:
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(prog) and ": error: " in lines[0], lines[0]
    assert needle in lines[0], lines[0]


# (argv template, what the one line must name, a path the refused command must not leave)
IN_PROCESS = {
    # section 3: an output location that cannot be written
    "dataset-proc": (["dataset", "--out", "/proc/x", "--param-sets", "1", "--per-set", "1"],
                     "/proc", None),
    "train-proc": (["train", "--data", "{ds}", "--out", "/proc/ck", "--epochs", "1", "--quiet",
                    "--arch", "mlp"], "/proc", None),
    "experiment-proc": (["experiment", "--tasks", "1", "--out", "/proc/x"], "/proc", None),
    "figures-out-file": (["figures", "--data", "{ds}", "--out", "{file}", "--epochs", "1"],
                         "existing file", None),
    # devices torch does not have
    "train-tpu": (["train", "--data", "{ds}", "--out", "{tmp}/ck", "--device", "tpu"], "tpu",
                  "{tmp}/ck.safetensors"),
    "bench-model-tpu": (["bench", "model", "--device", "tpu", "--arch", "mlp", "--train-steps",
                         "1", "--repeats", "1"], "tpu", None),
    # a dataset with a truncated shard
    "train-truncated": (["train", "--data", "{bad}", "--out", "{tmp}/ck", "--epochs", "1",
                         "--quiet", "--arch", "mlp"], "truncated", "{tmp}/ck.safetensors"),
    "figures-truncated": (["figures", "--data", "{bad}", "--out", "{tmp}/f", "--epochs", "1",
                           "--quiet"], "truncated", "{tmp}/f"),
    # numbers out of range, NaN, infinity
    "bench-sim-workers-0": (["bench", "sim", "--workers", "0", "--trajectories", "1",
                             "--rollouts", "1"], "--workers", None),
    "figures-seeds-negative": (["figures", "--data", "{ds}", "--out", "{tmp}/f", "--seeds",
                                "-1", "--epochs", "1"], "--seeds", "{tmp}/f"),
    "figures-lr-nan": (["figures", "--data", "{ds}", "--out", "{tmp}/f", "--lr", "nan",
                        "--epochs", "1"], "--lr", "{tmp}/f"),
    "sweep-lambda-inf": (["experiment", "sweep", "--checkpoint", "{model}", "--lambdas",
                          "0.1,inf", "--seeds", "0", "--n", "4", "--h", "1", "--out",
                          "{tmp}/s"], "inf", "{tmp}/s"),
    # section 4: silently accepted before
    "figures-epochs-0": (["figures", "--data", "{ds}", "--out", "{tmp}/f", "--epochs", "0",
                          "--quiet"], "--epochs", "{tmp}/f"),
    "figures-patience-negative": (["figures", "--data", "{ds}", "--out", "{tmp}/f", "--epochs",
                                   "1", "--patience", "-1", "--quiet"], "--patience", "{tmp}/f"),
    "train-threads-negative": (["train", "--data", "{ds}", "--out", "{tmp}/ck", "--threads",
                                "-1", "--epochs", "1", "--quiet", "--arch", "mlp"], "--threads",
                               "{tmp}/ck.safetensors"),
    # a parameter file that is not valid UTF-8, given to every command that takes one
    "dataset-latin1": (["dataset", "--out", "{tmp}/d", "--param-sets", "1", "--per-set", "1",
                        "--params-file", "{latin1}"], "not valid UTF-8", "{tmp}/d"),
    "train-latin1": (["train", "--data", "{ds}", "--out", "{tmp}/ck", "--params-file",
                      "{latin1}", "--epochs", "1", "--quiet", "--arch", "mlp"], "not valid UTF-8",
                     "{tmp}/ck.safetensors"),
    "figures-latin1": (["figures", "--data", "{ds}", "--out", "{tmp}/f", "--params-file",
                        "{latin1}", "--epochs", "1", "--quiet"], "not valid UTF-8", "{tmp}/f"),
    "experiment-latin1": (["experiment", "--tasks", "1", "--methods", "baseline1", "--no-oracle",
                           "--n-samples", "4", "--horizon", "1", "--out", "{tmp}/e",
                           "--params-file", "{latin1}"], "not valid UTF-8", "{tmp}/e"),
    "experiment-sim-latin1": (["experiment", "--tasks", "1", "--methods", "baseline1",
                               "--no-oracle", "--n-samples", "4", "--horizon", "1", "--out",
                               "{tmp}/e", "--sim-params", "{latin1}"], "not valid UTF-8",
                              "{tmp}/e"),
    "experiment-planner-latin1": (["experiment", "--tasks", "1", "--methods", "baseline1",
                                   "--no-oracle", "--n-samples", "4", "--horizon", "1", "--out",
                                   "{tmp}/e", "--planner-params", "{latin1}"], "not valid UTF-8",
                                  "{tmp}/e"),
    "experiment-learner-latin1": (["experiment", "--tasks", "1", "--methods", "ol-mppi",
                                   "--no-oracle", "--n-samples", "4", "--horizon", "1", "--out",
                                   "{tmp}/e", "--learner-params", "{latin1}"], "not valid UTF-8",
                                  "{tmp}/e"),
    "sweep-latin1": (["experiment", "sweep", "--checkpoint", "{model}", "--seeds", "0", "--n",
                      "4", "--h", "1", "--lambdas", "0.1", "--out", "{tmp}/s", "--sim-params",
                      "{latin1}"], "not valid UTF-8", "{tmp}/s"),
    # section 5: output folders holding other files or an earlier result
    "figures-foreign": (["figures", "--data", "{ds}", "--out", "{foreign}", "--epochs", "1",
                         "--quiet"], "not empty", None),
    "experiment-foreign": (["experiment", "--tasks", "1", "--methods", "baseline1",
                            "--no-oracle", "--n-samples", "4", "--horizon", "1", "--out",
                            "{foreign}"], "not empty", None),
    "sweep-foreign": (["experiment", "sweep", "--checkpoint", "{model}", "--seeds", "0", "--n",
                       "4", "--h", "1", "--lambdas", "0.1", "--out", "{foreign}"], "not empty",
                      None),
    "train-existing-checkpoint": (["train", "--data", "{ds}", "--out", "{model}", "--epochs", "1",
                                   "--quiet", "--arch", "mlp"], "already exists", None),
}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("case", sorted(IN_PROCESS))
def test_bad_input_is_one_line_exit_2(case: str, env, tmp_path, capsys) -> None:
    template, needle, absent = IN_PROCESS[case]
    argv = _argv(template, env, tmp_path)
    before = {p: p.stat().st_mtime_ns for p in env["root"].rglob("*") if p.is_file()}
    assert peel_main(argv) == 2
    out = capsys.readouterr()
    prog = "peel " + (" ".join(argv[:2]) if argv[0] == "bench" else argv[0])
    _one_line(out.err, prog, needle)
    assert out.out == ""  # nothing was run, so nothing was printed
    if absent is not None:
        assert not Path(_argv([absent], env, tmp_path)[0]).exists()
    assert list(tmp_path.iterdir()) == []  # no folder or file left behind
    after = {p: p.stat().st_mtime_ns for p in env["root"].rglob("*") if p.is_file()}
    assert after == before  # the fixture's files (checkpoint, foreign files) are untouched


def _run(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True,
                          timeout=timeout)


PEEL = ["-m", "peel_bringup.cli"]

# Commands that start processes or ROS: real processes, with a bound on their run time
PROCESSES = {
    "graph-proc": ([*PEEL, "graph", "--out", "/proc/x", "--tasks", "1"], "peel graph", "/proc"),
    "demo-proc": ([*PEEL, "demo", "--out", "/proc/x", "--tasks", "1"], "peel demo", "/proc"),
    "graph-record-proc": ([*PEEL, "graph", "--tasks", "1", "--record", "/proc/x/bag",
                           "--out", "{tmp}/run"], "peel graph", "/proc"),
    "graph-latin1": ([*PEEL, "graph", "--tasks", "1", "--params", "{latin1}", "--out",
                      "{tmp}/run"], "peel graph", "not valid UTF-8"),
    "demo-latin1": ([*PEEL, "demo", "--tasks", "1", "--params", "{latin1}", "--out",
                     "{tmp}/run"], "peel demo", "not valid UTF-8"),
    "graph-foreign": ([*PEEL, "graph", "--tasks", "1", "--out", "{foreign}"], "peel graph",
                      "not empty"),
    # a parameter file that sets nothing, and a folder where the file should be
    "graph-params-empty": ([*PEEL, "graph", "--tasks", "1", "--params", "{empty}", "--out",
                            "{tmp}/run"], "peel graph", "is empty: it names no node"),
    "demo-params-empty": ([*PEEL, "demo", "--tasks", "1", "--params", "{empty}", "--out",
                           "{tmp}/run"], "peel demo", "is empty: it names no node"),
    "graph-params-dir": ([*PEEL, "graph", "--tasks", "1", "--params", "{params_dir}", "--out",
                          "{tmp}/run"], "peel graph", "is a directory, not a parameter file"),
    "demo-params-dir": ([*PEEL, "demo", "--tasks", "1", "--params", "{params_dir}", "--out",
                         "{tmp}/run"], "peel demo", "is a directory"),
    "record-duration-inf": ([*PEEL, "record", "--out", "{tmp}/bag", "--duration", "inf"],
                            "peel record", "--duration"),
    "evaluate-non-finite": (["-m", "model_learner_node.evaluate", "{huge}", "{ds}"],
                            "python -m model_learner_node.evaluate", "non-finite"),
}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("case", sorted(PROCESSES))
def test_bad_input_to_a_process_is_one_line_exit_2(case: str, env, tmp_path) -> None:
    template, prog, needle = PROCESSES[case]
    proc = _run(_argv(template, env, tmp_path))
    assert proc.returncode == 2, proc.stdout + proc.stderr
    _one_line(proc.stderr, prog, needle)
    assert "started" not in proc.stdout  # no node was started
    assert list(tmp_path.iterdir()) == []


@pytest.mark.timeout(300)
def test_graph_refuses_an_earlier_run_unless_forced(env, tmp_path) -> None:
    """``peel graph --out DIR`` over an earlier run: refused, nothing mixed or deleted."""
    run = tmp_path / "run"
    (run / "models").mkdir(parents=True)
    (run / "models" / "model_v0002.safetensors").write_bytes(b"old")
    (run / "summary.json").write_text(json.dumps({"tasks": 3}))
    (run / ".peel_run.json").write_text(json.dumps({"command": "peel graph",
                                                    "created": "2025-01-01T00:00:00"}))
    proc = _run([*PEEL, "graph", "--tasks", "1", "--out", str(run)])
    assert proc.returncode == 2
    _one_line(proc.stderr, "peel graph", "earlier 'peel graph' run")
    assert "--force" in proc.stderr
    assert (run / "models" / "model_v0002.safetensors").read_bytes() == b"old"
    assert json.loads((run / "summary.json").read_text()) == {"tasks": 3}


def test_train_force_replaces_an_existing_checkpoint(env, tmp_path) -> None:
    out = tmp_path / "ck"
    for suffix in (".safetensors", ".json"):
        shutil.copy(env["model"].with_suffix(suffix), out.with_suffix(suffix))
    argv = ["train", "--data", str(env["ds"]), "--out", str(out), "--epochs", "1", "--quiet",
            "--arch", "mlp", "--threads", "1"]
    assert peel_main(argv) == 2  # refused without --force (the case above)
    assert peel_main([*argv, "--force"]) == 0
    assert load_checkpoint(out).arch == "mlp"
    assert json.loads(out.with_suffix(".metrics.json").read_text())["epochs_run"] == 1
