"""Evaluate a checkpoint on dataset splits: RMSE / Corr per channel (Eq. 39-40) as JSON.

    python -m model_learner_node.evaluate CKPT DIR [DIR ...] [--splits test]

Used for the sim-to-plant gap of docs/model.md: the shipped (simulator-trained) model on the
simulator's test split and on a ``peel dataset --source plant`` test split.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from peel_msgs_py.errors import PeelError

from .checkpoint import jsonable, load_checkpoint
from .metrics import evaluate, persistence_metrics
from .windows import stack_windows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m model_learner_node.evaluate",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", type=Path)
    p.add_argument("data", type=Path, nargs="+", help="dataset directories ('peel dataset')")
    p.add_argument("--splits", nargs="+", default=["test"], choices=["train", "val", "test"])
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from peel_sim_node.dataset import load_split

    pred = load_checkpoint(args.checkpoint)
    out: dict = {"checkpoint": str(args.checkpoint), "results": {}}
    for d in args.data:
        if not d.is_dir():
            raise PeelError(f"dataset {d} is not a directory")
        trajs = [t for s in args.splits for t in load_split(d, s)]
        m = evaluate(pred, trajs)
        source = json.loads((d / "dataset.json").read_text()).get("source") \
            if (d / "dataset.json").is_file() else None
        out["results"][str(d)] = {
            "source": source, "splits": args.splits, "n_trajectories": len(trajs),
            "rmse": m["rmse"], "corr": m["corr"], "n_samples": m["n_samples"],
            "persistence_rmse": persistence_metrics(stack_windows(trajs, pred.h))["rmse"],
        }
    print(json.dumps(jsonable(out), indent=2))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except PeelError as exc:
        print(f"model_learner_node.evaluate: error: {exc}", file=sys.stderr)
        sys.exit(2)
