"""``peel experiment ...`` (paper 4.4) and ``peel experiment sweep ...`` (Table 2, 4.5).

Both print a JSON summary on stdout (progress bars go to stderr) and write their files into
``--out``. Defaults come from ``config/peel_bringup.yaml`` (groups ``experiment`` and ``sweep``);
the command-line options override them.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from peel_msgs_py.cliargs import (
    ArgumentParser,
    float_list,
    int_list,
    nonnegative_int,
    positive_float,
    positive_int,
    run_main,
)
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import OutputDir, read_marker

from .experiment_config import ExperimentConfig, check_methods, load_experiment_config

_ints = int_list(0)  # comma-separated seeds / N / H
_floats = float_list(0.0, min_open=True)  # comma-separated lambdas: finite and > 0
_positive = positive_int


def _common(p: ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--force", action="store_true",
                   help="replace an earlier run in --out (never a folder peel did not write)")
    p.add_argument("--workers", type=_positive, help="worker processes (results do not "
                   "depend on it; default from config, 1)")
    p.add_argument("--n-samples", type=_positive, help="MPPI N (default 50)")
    p.add_argument("--horizon", type=_positive, help="MPPI H (default 5)")
    p.add_argument("--lambda", dest="lam", type=positive_float, help="MPPI lambda (default 0.1)")
    p.add_argument("--params-file", help="override file for config/peel_bringup.yaml")
    p.add_argument("--sim-params", help="override file for config/peel_sim_node.yaml")
    p.add_argument("--planner-params", help="override file for config/peel_planner_node.yaml")


def _effect_arg(p: ArgumentParser) -> None:
    p.add_argument("--effect", action="append", default=[], metavar="MODULE:FUNCTION",
                   help="add a user effect to the plant (peel_sim_node.effects interface, "
                        "docs/residual.md); repeatable")


# each override flag, the one node whose section it reads
_PARAM_FLAGS = (("params_file", "peel_bringup"), ("sim_params", "peel_sim_node"),
                ("planner_params", "peel_planner_node"), ("learner_params", "model_learner_node"))


def _check_param_files(args: argparse.Namespace) -> None:
    """Read every override file now: a missing, non-UTF-8 or malformed one is refused before
    any peel runs (the workers read them again), and so is a file with a section for a node
    other than its flag's, which that flag would pass over unread."""
    from peel_msgs_py.params import load_param_file, node_sections

    flag_of = {node: "--" + attr.replace("_", "-") for attr, node in _PARAM_FLAGS}
    for attr, node in _PARAM_FLAGS:
        path = getattr(args, attr, None)
        if not path:
            continue
        load_param_file(path, node)
        other = [n for n in node_sections(path) if n != node]
        if other:
            hint = f"; pass it with {flag_of[other[0]]}" if other[0] in flag_of else ""
            raise PeelError(f"{flag_of[node]} {path}: section '{other[0]}' is not read by "
                            f"{flag_of[node]}, which takes {node}'s parameters only{hint}")


def _base_cfg(args: argparse.Namespace) -> ExperimentConfig:
    _check_param_files(args)
    cfg = load_experiment_config(args.params_file)
    changes: dict[str, Any] = {}
    if args.workers is not None:
        changes["workers"] = args.workers
    if args.n_samples is not None:
        changes["n_samples"] = args.n_samples
    if args.horizon is not None:
        changes["horizon"] = args.horizon
    if args.lam is not None:
        if not args.lam > 0:
            raise PeelError(f"parameter 'lambda' must be > 0, got {args.lam}")
        changes["lam"] = args.lam
    return replace(cfg, **changes)


def experiment_parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="peel experiment",
        description="Consecutive peels on the plant per method, from one pretrained model "
                    "(paper 4.4): results.json, Fig. 11, Table 1, Fig. 12, report.md. "
                    "'peel experiment sweep --help' for Table 2, 'peel experiment grid --help' "
                    "for the levels, 'peel experiment fleet --help' for K cells against one.")
    p.add_argument("--tasks", type=_positive, help="peels per method (default 20)")
    p.add_argument("--methods", help="comma-separated: ol-mppi,baseline1,baseline2")
    seeds = p.add_mutually_exclusive_group()
    seeds.add_argument("--seed", type=nonnegative_int, help="one experiment seed")
    seeds.add_argument("--seeds", type=_ints, help="several seeds, e.g. 0,1,2 (aggregated)")
    p.add_argument("--checkpoint", help="pretrained model (default: the shipped checkpoint)")
    p.add_argument("--no-oracle", action="store_true", help="skip the oracle")
    p.add_argument("--no-save-model", action="store_true",
                   help="do not save OL-MPPI's last-task model")
    p.add_argument("--learner-params", help="override file for config/model_learner_node.yaml "
                   "(maml and baseline2 groups)")
    p.add_argument("--first-order", action="store_true", help="first-order MAML")
    _plant_args(p)
    _effect_arg(p)
    _common(p)
    return p


def _level(text: str) -> int:
    from peel_sim_node.plant import LEVELS

    try:
        val = int(text)
    except ValueError:
        val = -1
    if val not in LEVELS:
        raise argparse.ArgumentTypeError(f"expected a plant level {list(LEVELS)}, got {text!r}")
    return val


def _plant_args(p: ArgumentParser) -> None:
    from peel_sim_node.plant import SEQUENCES

    p.add_argument("--plant", dest="plant_level", type=_level, metavar="LEVEL",
                   help="plant severity level (0 = the simulator; default: plant.level of "
                        "config/peel_sim_node.yaml; docs/simulator.md)")
    p.add_argument("--sequence", choices=SEQUENCES,
                   help="how the pad changes over the peels (default: stationary)")


def sweep_parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="peel experiment sweep",
        description="Table 2 (4.5): N, H and lambda one factor at a time around the defaults, "
                    "one plant peel per value and seed with a fixed model.")
    p.add_argument("--checkpoint", required=True,
                   help="the model to plan with (e.g. OL-MPPI's task-20 model that "
                        "'peel experiment' saved)")
    p.add_argument("--seeds", type=_ints, help="seeds, one plant substrate each (default 0,1,2)")
    p.add_argument("--n", dest="n_values", type=_ints, help="N values (default 10,30,50,80,100)")
    p.add_argument("--h", dest="h_values", type=_ints, help="H values (default 1,3,5,7,10)")
    p.add_argument("--lambdas", type=_floats, help="lambda values (default "
                   "0.02,0.05,0.1,0.2,0.5)")
    _effect_arg(p)
    _common(p)
    return p


def _effects(specs: list[str]) -> tuple[str, ...]:
    """The ``--effect`` names, checked (imported) before anything is written or run."""
    from peel_sim_node.effects import load_effect

    for spec in specs:
        load_effect(spec)
    return tuple(specs)


def _checkpoint(path: str | None) -> str:
    if path is None:
        from peel_model.checkpoint import shipped_checkpoint

        return str(shipped_checkpoint())
    from peel_model.checkpoint import checkpoint_paths, read_checkpoint_config

    st_path, js_path = checkpoint_paths(path)
    if not st_path.is_file():
        raise PeelError(f"checkpoint '{path}' not found")
    read_checkpoint_config(js_path)  # fail early with a CheckpointError naming the problem
    return str(st_path)


def _summary(results: dict[str, Any]) -> dict[str, Any]:
    methods = {}
    for m, v in results["methods"].items():
        tasks = v["tasks"]
        methods[m] = {"cost_first": tasks[0]["cost"], "cost_last": tasks[-1]["cost"],
                      "outcomes": [t["outcome"] for t in tasks]}
    return {"out": results["files"], "methods": methods, "table1": results["table1"],
            "targets": results["targets"], "timing": results["timing"],
            "task20_model": results["task20_model"]}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = "peel experiment " + " ".join(shlex.quote(a) for a in argv)
    if argv and argv[0] == "sweep":
        return _sweep(argv[1:], command)
    if argv and argv[0] == "grid":
        return _grid(argv[1:], command)
    if argv and argv[0] == "fleet":
        return _fleet(argv[1:], command)
    args = experiment_parser().parse_args(argv)
    out = OutputDir(args.out, command="peel experiment", force=args.force)
    cfg = _base_cfg(args)
    changes: dict[str, Any] = {}
    if args.tasks is not None:
        changes["tasks"] = args.tasks
    if args.methods is not None:
        changes["methods"] = _methods(args.methods)
    if args.seed is not None:
        if args.seed < 0:
            raise PeelError(f"parameter 'seed' must be >= 0, got {args.seed}")
        changes["seeds"] = (args.seed,)
    if args.seeds is not None:
        changes["seeds"] = args.seeds
    if args.no_oracle:
        changes["oracle"] = False
    if args.no_save_model:
        changes["save_model"] = False
    if args.plant_level is not None:
        changes["plant_level"] = args.plant_level
    if args.sequence is not None:
        changes["sequence"] = args.sequence
    cfg = replace(cfg, **changes)
    effects = _effects(args.effect)
    from .experiment import run_experiment

    results = run_experiment(
        cfg, checkpoint=_checkpoint(args.checkpoint), out=out.create(),  # created after checks
        sim_overrides=args.sim_params, planner_overrides=args.planner_params,
        learner_overrides=args.learner_params, command=command,
        maml_changes={"first_order": True} if args.first_order else None,
        effects=effects)
    print(json.dumps(_summary(results), indent=1))
    return 0


def grid_parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="peel experiment grid",
        description="The experiment for every plant severity level and sequence, then one "
                    "report: OUT/summary.{md,json}, headroom.png, fig11_levels.png (and each "
                    "cell's own files in OUT/L<level>_<sequence>/; finished cells are reused).")
    p.add_argument("--levels", type=_ints, help="plant levels (default: all, 0,1,2,3)")
    p.add_argument("--sequences", help="comma-separated: stationary,drift,batch-switch "
                   "(default: all)")
    p.add_argument("--tasks", type=_positive, help="peels per method (default 20)")
    p.add_argument("--seeds", type=_ints, required=True,
                   help="seeds (at least 3 for confidence intervals), e.g. 100,101,102")
    p.add_argument("--checkpoint", help="pretrained model (default: the shipped checkpoint)")
    p.add_argument("--learner-params", help="override file for config/model_learner_node.yaml")
    p.add_argument("--methods", help="comma-separated arms beside the oracle (default "
                   "ol-mppi,baseline1,baseline2; ol-mppi-fast adds the fast step)")
    p.add_argument("--report-only", action="store_true",
                   help="run nothing: write the report from the cells already in --out")
    _common(p)
    return p


def _methods(text: str) -> tuple[str, ...]:
    """The arms of a comma-separated ``--methods``, each checked (one-line error otherwise)."""
    methods = tuple(m.strip() for m in text.split(",") if m.strip())
    check_methods(methods)
    return methods


def _grid(argv: list[str], command: str) -> int:
    from peel_sim_node.plant import LEVELS, SEQUENCES, check_level, check_sequence

    args = grid_parser().parse_args(argv)
    earlier = read_marker(args.out) if args.out.is_dir() else None
    resume = earlier is not None and earlier.get("command") == "peel experiment grid"
    out = None if resume else OutputDir(args.out, command="peel experiment grid", force=args.force)
    cfg = _base_cfg(args)
    levels = args.levels or LEVELS
    for lv in levels:
        check_level(lv)
    seqs = tuple(x.strip() for x in (args.sequences or ",".join(SEQUENCES)).split(",")
                 if x.strip())
    for sq in seqs:
        check_sequence(sq)
    methods = ("ol-mppi", "baseline1", "baseline2") if args.methods is None else _methods(args.methods)
    changes: dict[str, Any] = {"seeds": args.seeds, "oracle": True, "methods": methods,
                               "save_model": False}
    if args.tasks is not None:
        changes["tasks"] = args.tasks
    cfg = replace(cfg, **changes)
    from .grid import run_grid

    if out is not None:  # a new grid; an earlier grid's folder is resumed (its cells reused)
        out.create()
    summary = run_grid(cfg, levels=levels, sequences=seqs,
                       checkpoint=_checkpoint(args.checkpoint), out=args.out,
                       sim_overrides=args.sim_params, planner_overrides=args.planner_params,
                       learner_overrides=args.learner_params, command=command,
                       report_only=args.report_only)
    print(json.dumps({"out": summary["files"], "targets": summary["targets"],
                      "missing": summary["missing"]}, indent=1))
    return 0


def fleet_parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="peel experiment fleet",
        description="K cells and one learner (peel fleet) against one cell with the same number "
                    "of peels, on the plant: the fraction of headroom closed per cell's own task "
                    "and per peels learned (OUT/summary.{md,json}, headroom.png; finished runs "
                    "in OUT are reused).")
    p.add_argument("--cells", type=_positive, default=3, metavar="K", help="cells (default 3)")
    p.add_argument("--tasks", type=_positive, default=3, metavar="T",
                   help="tasks per cell (default 3; the one cell peels K x T)")
    p.add_argument("--seeds", type=_ints, required=True, help="fleet seeds, e.g. 950,951,952")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--force", action="store_true",
                   help="replace an earlier run in --out (never a folder peel did not write)")
    p.add_argument("--workers", type=_positive, help="worker processes of the in-process runs "
                   "(results do not depend on it; default from config, 1)")
    # the fleet runs the nodes' config as it is: no planner, plant or model options here, so
    # the in-process runs cannot differ from the fleet's
    return p


def _fleet(argv: list[str], command: str) -> int:
    args = fleet_parser().parse_args(argv)
    earlier = read_marker(args.out) if args.out.is_dir() else None
    if earlier is None or earlier.get("command") != "peel experiment fleet":
        OutputDir(args.out, command="peel experiment fleet", force=args.force).create()
    cfg = load_experiment_config(None)
    if args.workers is not None:
        cfg = replace(cfg, workers=args.workers)
    from .fleet_study import run_fleet_study

    summary = run_fleet_study(cfg, cells=args.cells, tasks=args.tasks, seeds=args.seeds,
                              out=args.out, checkpoint=_checkpoint(None), command=command)
    print(json.dumps({"out": summary["files"], "target": summary["target"],
                      "fleet_by_task": {k: v["closed"] for k, v in
                                        summary["fleet"]["by_task"].items()},
                      "one_cell_by_task": {k: v["closed"] for k, v in
                                           summary["one_cell"]["by_task"].items()}}, indent=1))
    return 0


def _sweep(argv: list[str], command: str) -> int:
    args = sweep_parser().parse_args(argv)
    out = OutputDir(args.out, command="peel experiment sweep", force=args.force)
    cfg = _base_cfg(args)
    changes: dict[str, Any] = {}
    for attr, key in (("seeds", "sweep_seeds"), ("n_values", "sweep_n"), ("h_values", "sweep_h"),
                      ("lambdas", "sweep_lambda")):
        if getattr(args, attr) is not None:
            changes[key] = getattr(args, attr)
    if any(v < 1 for v in changes.get("sweep_n", (1,)) + changes.get("sweep_h", (1,))):
        raise PeelError("parameter 'n'/'h' values must be >= 1")
    cfg = replace(cfg, **changes)
    effects = _effects(args.effect)
    from .experiment import run_sweep

    sweep = run_sweep(cfg, checkpoint=_checkpoint(args.checkpoint), out=out.create(),
                      sim_overrides=args.sim_params, planner_overrides=args.planner_params,
                      command=command, effects=effects)
    print(json.dumps({"out": sweep["files"], "table2": sweep["table2"],
                      "timing": sweep["timing"]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("peel experiment", main))
