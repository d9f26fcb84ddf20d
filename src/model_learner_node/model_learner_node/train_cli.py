"""``peel train``: offline training of the forward model (3.3) and fine-tuning from bags.

From a dataset written by ``peel dataset`` (splits train / val / test)::

    peel train --data DIR --arch {ours,mlp,cnn-lstm} [--no-pene] --out CKPT [--epochs E] [--seed S]

From recorded MCAP bags (the path real-robot data takes): the ``/peel/trajectory`` messages are
extracted with :func:`peel_bag.bagread.read_trajectories`, split by trajectory into a
training and a hold-out part (``--val-fraction``, seeded), and ``--init`` is fine-tuned; its
normalisation is kept::

    peel train --from-bags BAG [BAG ...] --init CKPT --out CKPT

Writes ``CKPT.safetensors`` + ``CKPT.json`` and ``CKPT.metrics.json`` (test RMSE / Corr per force
channel, Eq. 39-40, and the learning curve) and prints the metrics as JSON on stdout.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from peel_model.checkpoint import jsonable, load_checkpoint
from peel_model.config import ARCHS, load_model_config
from peel_msgs_py.cliargs import (
    ArgumentParser,
    float_arg,
    nonnegative_int,
    positive_float,
    positive_int,
)
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import check_output_files

from .config import load_train_config
from .devices import device_arg
from .train import output_paths, train_and_save


def build_parser() -> ArgumentParser:
    p = ArgumentParser(prog="peel train", description=__doc__.split("\n\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="dataset directory written by 'peel dataset'")
    src.add_argument("--from-bags", nargs="+", type=Path, metavar="BAG",
                     help="recorded rosbag2/MCAP bags with /peel/trajectory messages")
    p.add_argument("--out", type=Path, required=True, help="checkpoint path (name or .safetensors)")
    p.add_argument("--force", action="store_true", help="replace an existing checkpoint at --out")
    p.add_argument("--arch", choices=ARCHS, default=None, help="architecture (default: config)")
    p.add_argument("--init", type=Path, help="checkpoint to start from (required with --from-bags)")
    p.add_argument("--no-pene", action="store_true", help="train with L_MSE only (kappa = 0)")
    p.add_argument("--epochs", type=positive_int, help="maximum epochs (default: config train.epochs)")
    p.add_argument("--seed", type=nonnegative_int, help="seed (default: config train.seed)")
    p.add_argument("--lr", type=positive_float, help="Adam learning rate (default: config, paper 1e-4)")
    p.add_argument("--batch-size", type=positive_int, help="slices per batch (default: config)")
    p.add_argument("--patience", type=positive_int, help="early-stopping patience (default: config)")
    p.add_argument("--val-fraction", type=float_arg(0.0, 1.0, min_open=True), default=0.2,
                   help="--from-bags: share of trajectories held out for validation (0.2)")
    p.add_argument("--params-file", type=str, help="ROS 2 parameter YAML overriding the config")
    p.add_argument("--device", type=device_arg, default="cpu", help="cpu (default), cuda[:N], or auto")
    p.add_argument("--threads", type=nonnegative_int, default=0,
                   help="torch CPU threads (0 = torch default)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _split_bags(trajs: list, fraction: float, seed: int) -> tuple[list, list, str]:
    if not 0.0 < fraction < 1.0:
        raise PeelError(f"--val-fraction must be in (0, 1), got {fraction}")
    if len(trajs) < 2:
        return trajs, trajs, "train (only one trajectory in the bags)"
    order = np.random.default_rng(seed).permutation(len(trajs))
    n_val = min(len(trajs) - 1, max(1, round(fraction * len(trajs))))
    val = [trajs[i] for i in sorted(order[:n_val])]
    train = [trajs[i] for i in sorted(order[n_val:])]
    return train, val, "holdout"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    check_output_files(output_paths(args.out), force=args.force)  # before any training
    model_cfg = load_model_config(args.params_file)
    train_cfg = load_train_config(args.params_file)
    if args.data is not None:
        from peel_sim_node.dataset import check_dataset

        check_dataset(args.data)  # a missing or truncated shard: refused before loading
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    changes = {k: v for k, v in (("epochs", args.epochs), ("seed", args.seed), ("lr", args.lr),
                                  ("batch_size", args.batch_size), ("patience", args.patience))
               if v is not None}
    train_cfg = replace(train_cfg, **changes)
    init = load_checkpoint(args.init) if args.init else None
    if init is not None and getattr(init, "terms", None):
        raise PeelError(f"--init {args.init} has a compensation term (peel residual); offline "
                        "training takes a plain model (the learner node adapts a compensated "
                        "one online, its terms held)")
    if init is not None:
        if args.arch is not None and args.arch != init.arch:
            raise PeelError(f"--arch {args.arch} differs from the --init checkpoint's {init.arch}")
        model_cfg = init.cfg
    elif args.arch is not None:
        model_cfg = model_cfg.with_arch(args.arch)
    extra: dict = {"command": "peel train " + " ".join(argv or [])}
    if args.from_bags:
        if init is None:
            raise PeelError("--from-bags needs --init CKPT (the model to fine-tune)")
        from peel_bag.bagread import read_trajectories

        trajs = []
        for bag in args.from_bags:
            trajs += [t for t in read_trajectories(bag) if len(t) >= 2]
        if not trajs:
            raise PeelError("the bags hold no /peel/trajectory message with at least 2 samples")
        train, val, label = _split_bags(trajs, args.val_fraction, train_cfg.seed)
        test = val
        extra["bags"] = [str(b) for b in args.from_bags]
        extra["init"] = str(args.init)
    else:
        from peel_sim_node.dataset import load_split

        train, val, test = (load_split(args.data, s) for s in ("train", "val", "test"))
        label = "test"
        extra["data"] = str(args.data)
        manifest = args.data / "dataset.json"
        if manifest.is_file():
            try:
                man = json.loads(manifest.read_text())
            except json.JSONDecodeError:
                raise PeelError(f"dataset manifest {manifest} is not valid JSON") from None
            extra["dataset"] = {k: man.get(k) for k in ("format", "code_version", "config_hash",
                                                       "source", "seed", "param_sets", "per_set")}
        if init is not None:
            extra["init"] = str(args.init)
    _, metrics = train_and_save(
        args.out, train, val, test, model_cfg=model_cfg, train_cfg=train_cfg,
        use_pene=not args.no_pene, init=init, device=args.device, progress=not args.quiet,
        extra_meta=extra, test_label=label,
    )
    print(json.dumps(jsonable(metrics), indent=2))
    return 0
