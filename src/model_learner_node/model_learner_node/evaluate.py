"""Evaluate a checkpoint on dataset splits: RMSE / Corr per channel (Eq. 39-40) as JSON.

    python -m model_learner_node.evaluate CKPT DIR [DIR ...] [--splits test]

Used for the sim-to-plant gap of docs/model.md: the shipped (simulator-trained) model on the
simulator's test split and on a ``peel dataset --source plant`` test split.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import torch

from peel_model.checkpoint import jsonable, load_checkpoint
from peel_model.validation import check_finite_outputs
from peel_model.windows import stack_windows
from peel_msgs_py.cliargs import ArgumentParser, run_main
from peel_msgs_py.errors import PeelError

from .metrics import evaluate_windows, persistence_metrics

PROG = "python -m model_learner_node.evaluate"


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", type=Path)
    p.add_argument("data", type=Path, nargs="+", help="dataset directories ('peel dataset')")
    p.add_argument("--splits", nargs="+", default=["test"], choices=["train", "val", "test"])
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from peel_sim_node.dataset import check_dataset, load_split

    pred = load_checkpoint(args.checkpoint)
    check_finite_outputs(pred, what=f"checkpoint {args.checkpoint}")
    manifests = {d: check_dataset(d) for d in args.data}
    out: dict = {"checkpoint": str(args.checkpoint), "results": {}}
    for d in args.data:
        trajs = [t for s in args.splits for t in load_split(d, s)]
        win = stack_windows(trajs, pred.h)
        if len(win) == 0:
            raise PeelError(f"dataset {d}: the splits {args.splits} hold no usable samples")
        m = evaluate_windows(pred, win)
        if not all(math.isfinite(v) for v in m["rmse"].values()):
            raise PeelError(f"checkpoint {args.checkpoint} predicts non-finite forces on {d} "
                            f"(RMSE {m['rmse']}): the model is not usable")
        out["results"][str(d)] = {
            "source": manifests[d].get("source"), "splits": args.splits,
            "n_trajectories": len(trajs),
            "rmse": m["rmse"], "corr": m["corr"], "n_samples": m["n_samples"],
            "persistence_rmse": persistence_metrics(win)["rmse"],
        }
    print(json.dumps(jsonable(out), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(PROG, main))
