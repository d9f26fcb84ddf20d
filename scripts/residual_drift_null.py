#!/usr/bin/env python3
"""False-alarm rate of the drift-across-tasks flag on clean plant data (its null calibration).

    .venv/bin/python scripts/residual_drift_null.py --out DIR [--seeds 100:1100] [--tasks 10,30]
        [--level L] [--alpha A]

``peel residual`` flags a drift across tasks on a force channel when the measured force at each
task's first sample changes with the task order (``peel_residual.analysis.start_force_drift``).
That sample is the blade at rest at C, before any command, so the flag's behaviour on clean data
depends on the plant's task-to-task scatter only: no model, no command profile. Each data seed
``s`` gives the first samples of ``n`` clean plant tasks exactly as ``scripts/residual_study.py``
records them (``exploratory_tasks``: task i reset with noise seed ``1000 s + i``), and the flag
is applied to them. Writes ``DIR/drift_null.json`` (every seed's p-values) and
``DIR/drift_null.md`` (the rates with Wilson 95 % intervals); prints the summary as JSON.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.cliargs import ArgumentParser, float_arg, int_arg, int_list, run_main


def seed_range(text: str) -> range:
    """``A:B`` (B excluded) as a range of data seeds."""
    a, _, b = text.partition(":")
    try:
        r = range(int(a), int(b))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B with integers A < B, got {text!r}") from None
    if not r:
        raise argparse.ArgumentTypeError(f"empty range {text!r}")
    return r


def first_samples(seed: int, n: int, level: int | None) -> np.ndarray:
    """``[n, 2]``: (F_RX, F_RZ) at t = 0 of the ``n`` clean plant tasks of data seed ``seed``."""
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv

    env = PeelEnv(load_sim_config(), source="plant", seed=seed, level=level)
    try:
        rows = []
        for i in range(n):
            h = env.reset(seed=seed * 1000 + i)
            rows.append([h.fx[0], h.fz[0]])
    finally:
        env.close()
    return np.array(rows)


def calibrate(seeds: range, n: int, level: int | None, alpha: float) -> dict[str, Any]:
    """The flag on each seed's first samples; per channel and either: flagged / seeds."""
    from peel_experiments.bench_common import wilson
    from peel_residual.analysis import start_force_drift

    runs = []
    for s in seeds:
        flags = start_force_drift(first_samples(s, n, level), alpha)
        runs.append({"seed": s, "p": [f["p"] for f in flags],
                     "drift": [bool(f["drift"]) for f in flags]})
    flagged = np.array([r["drift"] for r in runs])
    k = {"fx": int(flagged[:, 0].sum()), "fz": int(flagged[:, 1].sum()),
         "either": int(flagged.any(axis=1).sum())}
    return {"n_tasks": n, "seeds": len(runs), "alpha": alpha, "flagged": k,
            "rate": {c: v / len(runs) for c, v in k.items()},
            "wilson95": {c: wilson(v, len(runs)) for c, v in k.items()}, "runs": runs}


def markdown(rows: list[dict[str, Any]], command: str) -> str:
    L = ["# Drift across tasks on clean plant data: false alarms", "", f"Command: `{command}`",
         "", "| tasks | data seeds | alpha per channel | flagged F_RX | flagged F_RZ | either "
         "channel | rate (Wilson 95 %) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["wilson95"]["either"]
        L.append(f"| {r['n_tasks']} | {r['seeds']} | {r['alpha']:g} | {r['flagged']['fx']} | "
                 f"{r['flagged']['fz']} | {r['flagged']['either']} | "
                 f"{r['rate']['either']:.1%} ({lo:.1%}-{hi:.1%}) |")
    return "\n".join(L) + "\n"


def main(argv: list[str]) -> int:
    from peel_residual.config import load_residual_config

    p = ArgumentParser(prog="residual_drift_null.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seeds", type=seed_range, default=seed_range("100:1100"),
                   help="data seeds A:B (B excluded); default 100:1100")
    p.add_argument("--tasks", type=int_list(3), default=(10, 30))
    p.add_argument("--level", type=int_arg(0, 3), default=None)
    p.add_argument("--alpha", type=float_arg(1e-6, 0.5), default=None,
                   help="significance per channel (default: residual.drift_alpha)")
    args = p.parse_args(argv)
    alpha = args.alpha if args.alpha is not None else load_residual_config().drift_alpha
    rows = [calibrate(args.seeds, n, args.level, alpha) for n in args.tasks]
    command = "scripts/residual_drift_null.py " + " ".join(shlex.quote(a) for a in argv)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "drift_null.json").write_text(json.dumps(
        {"command": command, "level": args.level, "rows": rows}, indent=1) + "\n")
    (args.out / "drift_null.md").write_text(markdown(rows, command))
    print(json.dumps([{k: v for k, v in r.items() if k != "runs"} for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("residual_drift_null.py", main))
