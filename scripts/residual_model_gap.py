#!/usr/bin/env python3
"""How far a model drifts open loop on clean plant tasks that no study analysed.

    .venv/bin/python scripts/residual_model_gap.py --seed S --model NAME=CHECKPOINT ... \
        [--tasks 20] [--level L]

Records ``--tasks`` clean exploratory tasks of data seed :data:`GAP_SEED` + S on the plant at
severity ``--level`` (default ``plant.level`` of config/peel_sim_node.yaml; 0 is the
simulator) with the study's generator (``scripts/residual_study.py``; none of these tasks is
analysed, adapted on or fresh there) and
prints, as JSON, per model and force channel (fx, fz in N) the RMSE of the open-loop rollout
over the planner's horizon (25 model steps, from every 5th sample, ``peel_residual.predict``),
its RMSE at the horizon's end (2.5 s) and its mean there (the systematic drift: predicted minus
measured, > 0 where the model over-predicts).
``--model shipped`` names the shipped checkpoint.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from peel_msgs_py.cliargs import ArgumentParser, int_arg, nonnegative_int, run_main

#: Data seed offset of the gap's clean tasks (the study uses 777_000 to adapt, 999_999 fresh).
GAP_SEED = 555_000


def gap(model: Any, tasks: list[Any]) -> dict[str, list[float]]:
    """Open-loop error of ``model`` on ``tasks`` (module docstring)."""
    import numpy as np

    from peel_residual.data import horizons
    from peel_residual.predict import open_loop

    h = int(model.h)
    hz = horizons(tasks, h, 25, 5)
    err = open_loop(model, hz) - hz.rows[:, h:, 2:4]
    end = err[:, -1][hz.valid[:, -1]]
    return {"rmse_over_horizon": np.sqrt((err[hz.valid] ** 2).mean(0)).round(3).tolist(),
            "rmse_at_end": np.sqrt((end ** 2).mean(0)).round(3).tolist(),
            "mean_at_end": end.mean(0).round(3).tolist()}


def main(argv: list[str]) -> int:
    p = ArgumentParser(prog="residual_model_gap.py", description=__doc__.split("\n")[1])
    p.add_argument("--seed", type=nonnegative_int, required=True)
    p.add_argument("--tasks", type=int_arg(1), default=20)
    p.add_argument("--level", type=int, choices=range(4), default=None, metavar="L",
                   help="plant severity level 0-3 (default: plant.level)")
    p.add_argument("--model", action="append", required=True, metavar="NAME=CHECKPOINT")
    args = p.parse_args(argv)
    models = {}
    for item in args.model:
        name, _, path = item.partition("=")
        if name != "shipped" and not path:
            p.error(f"--model {item!r}: expected NAME=CHECKPOINT")
        models[name] = path
    import torch

    from peel_model.checkpoint import load_checkpoint, shipped_checkpoint

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from residual_study import _tasks

    torch.set_num_threads(1)
    tasks = list(_tasks("plant", args.tasks, GAP_SEED + args.seed, args.level))
    out: dict[str, Any] = {"tasks": args.tasks, "data_seed": GAP_SEED + args.seed,
                           "level": args.level, "channels": ["fx", "fz"]}
    for name, path in models.items():
        out[name] = {"checkpoint": path or "shipped",
                     **gap(load_checkpoint(path or shipped_checkpoint()), tasks)}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("residual_model_gap.py", main))
