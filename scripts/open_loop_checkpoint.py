#!/usr/bin/env python3
"""A pretrained model fine-tuned open loop on the offline dataset (3.3 plus the rollout loss).

    .venv/bin/python scripts/open_loop_checkpoint.py --data DS --out PREFIX \
        [--checkpoint CKPT] [--epochs 60] [--threads 2] [--force]

Reads the train and val splits of a ``peel dataset`` folder DS (the data the shipped model was
trained on one step ahead, Eq. 23-25), fine-tunes ``--checkpoint`` (default: the shipped one)
with the loss of its own rollout over the planner's horizon
(:func:`peel_residual.adapt.open_loop_finetune`: 25 model steps fed the measured speeds and its
own forces, early stopping on the val split's open-loop MSE) and writes
``PREFIX.safetensors`` + ``PREFIX.json`` (atomically, :func:`peel_model.checkpoint.save_checkpoint`;
an existing PREFIX only with ``--force``, checked before any training).
The meta keeps the starting model's record and adds ``open_loop_tuned`` (the validation MSE in
N^2 per epoch, index 0 before, the best epoch, the settings and the starting file's SHA-256).
Prints the same as JSON. docs/planner.md ("A model tuned open loop") measures what the planner
does with it.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from peel_msgs_py.cliargs import ArgumentParser, int_arg, run_main


def main(argv: list[str]) -> int:
    p = ArgumentParser(prog="open_loop_checkpoint.py", description=__doc__.split("\n")[1])
    p.add_argument("--data", required=True, help="a peel dataset folder (train and val splits)")
    p.add_argument("--out", required=True, help="checkpoint prefix: writes PREFIX.safetensors/.json")
    p.add_argument("--checkpoint", default="", help="starting model (default: the shipped one)")
    p.add_argument("--epochs", type=int_arg(1), default=None, help="at most (default 60)")
    p.add_argument("--threads", type=int_arg(1), default=2, help="torch threads")
    p.add_argument("--force", action="store_true", help="replace an existing PREFIX checkpoint")
    args = p.parse_args(argv)
    out = Path(args.out)
    if not out.parent.is_dir():
        p.error(f"--out {args.out}: folder {out.parent} does not exist")
    if out.with_suffix(".safetensors").exists() and not args.force:
        p.error(f"--out {args.out}: {out.name}.safetensors exists (--force replaces it)")
    import torch

    from peel_model.checkpoint import (
        load_checkpoint,
        read_checkpoint_config,
        save_checkpoint,
        shipped_checkpoint,
    )
    from peel_residual.adapt import OpenLoopTune, open_loop_finetune
    from peel_sim_node.dataset import load_split

    torch.set_num_threads(args.threads)
    start = Path(args.checkpoint) if args.checkpoint else shipped_checkpoint()
    cfg = OpenLoopTune() if args.epochs is None else replace(OpenLoopTune(), epochs=args.epochs)
    train, val = load_split(args.data, "train"), load_split(args.data, "val")
    result = open_loop_finetune(load_checkpoint(start), train, val, cfg)
    record: dict[str, Any] = {
        "val_mse": result.val_mse, "best_epoch": result.best_epoch, "settings": asdict(cfg),
        "data": str(Path(args.data).resolve()), "train_tasks": len(train), "val_tasks": len(val),
        "tuned_from": start.name,
        "tuned_from_sha256": hashlib.sha256(start.read_bytes()).hexdigest()}
    meta = {**read_checkpoint_config(start).get("meta", {}), "open_loop_tuned": record}
    path = save_checkpoint(args.out, result.model, meta)
    print(json.dumps({"checkpoint": str(path), **record}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("open_loop_checkpoint.py", main))
