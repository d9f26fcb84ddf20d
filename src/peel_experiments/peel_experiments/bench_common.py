"""What the planner benchmarks share (``peel bench planner``, ``peel bench safety``): the model
they plan with, the ``--set NAME=VALUE`` planner overrides, the timing of one call, and the
intervals they report (a mean's, a rate's)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import load_planner_config


def load_model() -> tuple[Any, dict[str, Any]]:
    """The shipped checkpoint, else a fresh ``ours`` ForcePredictor (seed 0)."""
    from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
    from peel_model.config import ModelConfig
    from peel_model.predictor import ForcePredictor

    try:
        path = shipped_checkpoint()
        pred = load_checkpoint(path)
        info = {"source": "shipped_checkpoint", "path": str(path)}
    except PeelError:
        torch.manual_seed(0)
        pred = ForcePredictor(ModelConfig())
        info = {"source": "fresh_untrained", "path": None}
    pred.eval()
    info.update({"arch": pred.arch, "h": pred.h,
                 "parameters": int(sum(p.numel() for p in pred.parameters()))})
    return pred, info


def timing(fn: Any, history: Trajectory, repeats: int,
           warmup: int = 3) -> tuple[float, float, float]:
    """Median and p99 wall time of one call (ms), and the median CPU time of the process
    (all its threads; on a loaded machine less disturbed than the wall time)."""
    for _ in range(warmup):
        fn(history)
    ts, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn(history)
        ts.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return float(np.median(ts)), float(np.percentile(ts, 99)), float(np.median(cpu))


def parse_sets(items: list[str]) -> dict[str, Any]:
    """``NAME=VALUE`` pairs -> {name: value} with YAML scalars (numbers, strings)."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise PeelError(f"--set {item!r}: expected NAME=VALUE, e.g. cost.barrier.weight=4")
        out[name.strip()] = yaml.safe_load(value)
    if out:
        load_planner_config().replace(**out)  # unknown names / bad values fail here, named
    return out


def interval(x: list[float]) -> dict[str, float]:
    """Mean and its 95 % interval, mean +- 1.96 standard errors."""
    a = np.asarray(x, dtype=float)
    half = 1.96 * a.std(ddof=1) / np.sqrt(len(a)) if len(a) > 1 else float("nan")
    return {"mean": round(float(a.mean()), 4), "ci95": [round(float(a.mean() - half), 4),
                                                        round(float(a.mean() + half), 4)]}


def wilson(k: int, n: int) -> list[float]:
    """95 % Wilson score interval of a rate k / n (z = 1.96); [0, 1] for n = 0."""
    if n == 0:
        return [0.0, 1.0]
    z, p = 1.96, k / n
    mid = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [round(float(max(0.0, mid - half)), 5), round(float(min(1.0, mid + half)), 5)]
