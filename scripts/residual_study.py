#!/usr/bin/env python3
"""Power and false-alarm rate of ``peel residual`` on random undeclared effects.

    .venv/bin/python scripts/residual_study.py --out DIR [--families F,...]
        [--amplitudes 0.5,1,2] [--tasks 10,30] [--draws 20] [--clean 20] [--seed 1]
        [--source plant|sim] [--level L] [--fresh 5] [--adapt K [--adapt-open-loop]] [--open-loop-fit]
        [--workers 1] [--no-progress]

Clean tasks are recorded once per data seed with the plant's episode generator under
exploratory command profiles (``peel_sim_node.episode.exploratory_tasks``, as
``scripts/residual_scenarios.py``); each effect job adds one drawn effect to them on the
measurement side (a speed family: records them again from the same seeds with the drawn speed
error in the plant, ``peel_sim_node.example_effects.SpeedError``) and runs the analysis of
``peel residual`` with the shipped model
(``peel_residual.study``, docs/residual.md "Power and false-alarm rate"). The
fresh tasks (``--fresh`` per task count, their own data seed) are never analysed: the corrected
model is scored on them with the same effect. Writes ``DIR/runs.jsonl`` (each run as it ends),
then ``DIR/study.json`` (every run and the summary) and ``DIR/study.md`` (the tables). Seeded:
the same arguments give the same results with any ``--workers``. Tune on dev seeds (``--seed 0``), report on others.

``--adapt K`` (K >= 8) analyses with *a model adapted to the plant* instead of the shipped one:
the shipped model fine-tuned on K clean tasks of their own data seed (:data:`ADAPT_SEED` + seed,
never analysed) as ``peel train --init`` fine-tunes (``train_and_save``, the ``train:`` group
with the Adam rate ``--adapt-lr``; 4 tasks validate, 2 test), written to
``DIR/adapted.safetensors`` with its metrics and named in ``study.json`` (``model``). It stands
for the cell's model after online learning on the plant: the plant's own difference is then in
the model, not in the residual.
With ``--adapt-open-loop`` that model is then fine-tuned on the same
tasks with the loss of its own rollout over the planner's horizon (``peel_residual.adapt``), so
that its open-loop drift on the plant is in the model too. ``adapted.safetensors`` is then the
open-loop-tuned model, recorded under ``open_loop_tuned`` (in ``study.json``'s ``model`` and the
checkpoint's meta); ``adapted.metrics.json`` and ``model``'s ``val_rmse_*`` / ``test_rmse``
describe the one-step stage before it.
"""

from __future__ import annotations

import hashlib
import json
import shlex
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import Any

from peel_msgs_py.cliargs import (
    ArgumentParser,
    float_arg,
    float_list,
    int_arg,
    int_list,
    nonnegative_int,
    positive_int,
    run_main,
)

FRESH_SEED = 999_999
#: Data seed offset of ``--adapt``'s clean tasks (none of them is analysed or fresh).
ADAPT_SEED = 777_000
#: ``--adapt``'s Adam rate, chosen on dev seed 0 (docs/residual.md): 10x the ``train:`` group's
#: 1e-4, which early-stops after a few epochs with most of the plant's open-loop gap left.
ADAPT_LR = 1e-3


@lru_cache(maxsize=8)
def _tasks(source: str, n: int, seed: int, level: int | None,
           speed_error: tuple[float, float] | None = None) -> tuple[Any, ...]:
    """``n`` clean tasks of data seed ``seed``; with ``speed_error`` = (scale, offset mm/s)
    the same tasks recorded with the robot at u * scale + offset (a plant-side speed draw)."""
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.episode import exploratory_tasks
    from peel_sim_node.example_effects import SpeedError

    effects = [SpeedError(*speed_error)] if speed_error else []
    return tuple(exploratory_tasks(load_sim_config(), source=source, n=n, seed=seed,
                                   effects=effects, level=level if source == "plant" else None))


@lru_cache(maxsize=1)
def _model_and_config(path: str | None, open_loop_fit: bool, heldout_alpha: float
                      ) -> tuple[Any, Any]:
    import torch

    from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
    from peel_residual.config import load_residual_config

    torch.set_num_threads(1)
    return (load_checkpoint(path or shipped_checkpoint()),
            load_residual_config(open_loop_fit=open_loop_fit, heldout_alpha=heldout_alpha))


def _adapt(out: Path, k: int, lr: float, source: str, seed: int, level: int | None,
           open_loop: bool = False) -> dict[str, Any]:
    """The shipped model fine-tuned on ``k`` clean tasks (module docstring, ``--adapt``), then,
    with ``open_loop``, on the same tasks with the open-loop loss (``--adapt-open-loop``)."""
    import torch

    from model_learner_node.config import load_train_config
    from model_learner_node.train import train_and_save
    from peel_model.checkpoint import (
        load_checkpoint,
        read_checkpoint_config,
        save_checkpoint,
        shipped_checkpoint,
    )
    from peel_residual.adapt import OpenLoopTune, open_loop_finetune

    torch.set_num_threads(1)
    tasks = list(_tasks(source, k, ADAPT_SEED + seed, level))
    init = load_checkpoint(shipped_checkpoint())
    cfg = replace(load_train_config(), lr=lr)
    result, metrics = train_and_save(out / "adapted", tasks[:-6], tasks[-6:-2], tasks[-2:],
                                     model_cfg=init.cfg, train_cfg=cfg,
                                     init=init, progress=False,
                                     extra_meta={"adapted_on": {"tasks": k, "source": source,
                                                                "data_seed": ADAPT_SEED + seed,
                                                                "level": level}})
    path = out / "adapted.safetensors"
    tuned: dict[str, Any] = {}
    if open_loop:
        ol = open_loop_finetune(load_checkpoint(path), tasks[:-6], tasks[-6:-2], OpenLoopTune())
        save_checkpoint(out / "adapted", ol.model,
                        {**read_checkpoint_config(path).get("meta", {}),
                         "open_loop_tuned": {"val_mse": ol.val_mse, "best_epoch": ol.best_epoch}})
        tuned = {"open_loop_tuned": {"val_mse_before": ol.val_mse[0],
                                     "val_mse_after": min(ol.val_mse),
                                     "best_epoch": ol.best_epoch,
                                     "epochs_run": len(ol.val_mse) - 1}}
    return {"adapted_on_tasks": k, "data_seed": ADAPT_SEED + seed, "lr": lr, **tuned,
            "checkpoint": path.name, "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "val_rmse_before": result.history[0]["val_rmse"],
            "val_rmse_after": result.best_val_rmse, "test_rmse": metrics["test_rmse"],
            "epochs_run": metrics["epochs_run"]}


def _run(args: tuple[Any, str, int | None, int, str | None, bool, float]) -> dict[str, Any]:
    from peel_residual.study import run_job

    job, source, level, fresh, model_path, open_loop_fit, heldout_alpha = args
    model, cfg = _model_and_config(model_path, open_loop_fit, heldout_alpha)
    inj = job.injection()
    speed = inj.speed_error() if inj is not None and inj.plant_side else None
    return run_job(job, _tasks(source, job.n_tasks, job.data_seed, level, speed),
                   _tasks(source, fresh, FRESH_SEED + job.seed, level, speed), model, cfg)


def main(argv: list[str]) -> int:
    from peel_residual.inject import STUDY_FAMILIES

    p = ArgumentParser(prog="residual_study.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--families", default=",".join(STUDY_FAMILIES))
    p.add_argument("--amplitudes", type=float_list(0.0), default=(0.5, 1.0, 2.0))
    p.add_argument("--tasks", type=int_list(4), default=(10, 30))
    p.add_argument("--draws", type=positive_int, default=20)
    p.add_argument("--clean", type=nonnegative_int, default=20)
    p.add_argument("--seed", type=nonnegative_int, default=1)
    p.add_argument("--source", choices=("plant", "sim"), default="plant")
    p.add_argument("--level", type=int_arg(0, 3), default=None)
    p.add_argument("--fresh", type=int_arg(2), default=5)
    p.add_argument("--adapt", type=nonnegative_int, default=0,
                   help="analyse with the shipped model fine-tuned on this many clean tasks "
                        "(0: the shipped model; else at least 8)")
    p.add_argument("--adapt-lr", type=float_arg(1e-6, 1.0), default=ADAPT_LR,
                   help=f"Adam rate of --adapt's fine-tuning (default {ADAPT_LR:g})")
    p.add_argument("--adapt-open-loop", action="store_true",
                   help="after --adapt's one-step fine-tuning, fine-tune on the same tasks with "
                        "the open-loop loss over the planner's horizon (peel_residual.adapt)")
    p.add_argument("--open-loop-fit", action="store_true",
                   help="analyse with the output-error fit (residual.open_loop_fit: true)")
    p.add_argument("--heldout-alpha", type=float_arg(0.0, 0.5), default=0.0,
                   help="residual.heldout_alpha: the held-out tasks' paired test of each kept "
                        "term (0: off, the default)")
    p.add_argument("--workers", type=positive_int, default=1)
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    unknown = sorted(set(families) - set(STUDY_FAMILIES))
    if unknown:
        p.error(f"unknown families {unknown}; known: {', '.join(STUDY_FAMILIES)}")
    if 0 < args.adapt < 8:
        p.error(f"--adapt needs at least 8 tasks (train, 4 validate, 2 test), got {args.adapt}")
    if args.adapt_open_loop and not args.adapt:
        p.error("--adapt-open-loop needs --adapt K")
    return _study(args, families, argv)


def _study(args: Any, families: list[str], argv: list[str]) -> int:
    from tqdm import tqdm

    from peel_residual.study import markdown, plan_jobs, summarise

    jobs = plan_jobs(families, args.amplitudes, args.tasks, args.draws, args.clean, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    model: dict[str, Any] = {"checkpoint": "shipped"}
    path = None
    if args.adapt:
        model = _adapt(args.out, args.adapt, args.adapt_lr, args.source, args.seed, args.level,
                       args.adapt_open_loop)
        path = str(args.out / "adapted.safetensors")
    work = [(j, args.source, args.level, args.fresh, path, args.open_loop_fit,
             args.heldout_alpha) for j in jobs]
    records: list[dict[str, Any]] = []
    with tqdm(total=len(jobs), desc="residual study", unit="run",
              disable=args.no_progress) as bar, open(args.out / "runs.jsonl", "w") as log:
        def done(rec: dict[str, Any]) -> None:  # each run as it ends: a cut study keeps them
            records.append(rec)
            log.write(json.dumps(rec) + "\n")
            log.flush()
            bar.update(1)

        if args.workers == 1:
            for w in work:
                done(_run(w))
        else:
            with ProcessPoolExecutor(args.workers) as pool:
                for rec in pool.map(_run, work, chunksize=1):
                    done(rec)
    records.sort(key=lambda r: r["index"])
    summary = summarise(records)
    command = "scripts/residual_study.py " + " ".join(shlex.quote(a) for a in argv)
    (args.out / "study.json").write_text(json.dumps(
        {"command": command, "source": args.source, "level": args.level, "seed": args.seed,
         "model": model, "open_loop_fit": args.open_loop_fit,
         "heldout_alpha": args.heldout_alpha, "summary": summary,
         "runs": records}, indent=1) + "\n")
    (args.out / "study.md").write_text(markdown(summary, command))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("residual_study.py", main))
