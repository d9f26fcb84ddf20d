"""``peel dataset``: generate a simulator or plant dataset (section 3.2, 4.3)."""

from __future__ import annotations

import json

from peel_msgs_py.cliargs import ArgumentParser, nonnegative_int, positive_int
from peel_msgs_py.outputs import check_location

from .config import load_sim_config
from .dataset import generate_dataset


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel dataset``; returns the exit status."""
    cfg0 = load_sim_config()
    ds = cfg0.dataset
    ap = ArgumentParser(prog="peel dataset", description=__doc__)
    ap.add_argument("--param-sets", type=positive_int, default=ds.param_sets,
                    help=f"K parameter sets P_k (default {ds.param_sets}; paper 1000)")
    ap.add_argument("--per-set", type=positive_int, default=ds.per_set,
                    help=f"M trajectories per set (default {ds.per_set}; paper 50)")
    ap.add_argument("--out", required=True, help="output directory (created; resumable)")
    ap.add_argument("--workers", type=positive_int, default=ds.workers, help="worker processes")
    ap.add_argument("--seed", type=nonnegative_int, default=ds.seed, help="dataset seed")
    ap.add_argument("--source", choices=("sim", "plant"), default="sim",
                    help="pretraining simulator or reality-gap plant")
    ap.add_argument("--params-file", default=None,
                    help="ROS 2 parameter YAML overriding config/peel_sim_node.yaml")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    a = ap.parse_args(argv)
    check_location(a.out)
    cfg = load_sim_config(a.params_file) if a.params_file else cfg0
    man = generate_dataset(cfg, a.out, param_sets=a.param_sets, per_set=a.per_set, seed=a.seed,
                           source=a.source, workers=a.workers, progress=not a.no_progress)
    print(json.dumps({"out": a.out, "splits": man["splits"], "source": a.source,
                      "seed": a.seed}))
    return 0
