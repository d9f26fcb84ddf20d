#!/usr/bin/env python3
"""Power and false-alarm rate of ``peel residual`` on random undeclared effects.

    .venv/bin/python scripts/residual_study.py --out DIR [--families F,...]
        [--amplitudes 0.5,1,2] [--tasks 10,30] [--draws 20] [--clean 20] [--seed 1]
        [--source plant|sim] [--level L] [--fresh 5] [--workers 1] [--no-progress]

Clean tasks are recorded once per data seed with the plant's episode generator under
exploratory command profiles (``peel_sim_node.episode.exploratory_tasks``, as
``scripts/residual_scenarios.py``); each effect job adds one drawn effect to them on the
measurement side and runs the analysis of ``peel residual`` with the shipped model
(``peel_residual.study``, docs/residual.md "Power and false-alarm rate"). The
fresh tasks (``--fresh`` per task count, their own data seed) are never analysed: the corrected
model is scored on them with the same effect. Writes ``DIR/runs.jsonl`` (each run as it ends),
then ``DIR/study.json`` (every run and the summary) and ``DIR/study.md`` (the tables). Seeded:
the same arguments give the same results with any ``--workers``. Tune on dev seeds (``--seed 0``), report on others.
"""

from __future__ import annotations

import json
import shlex
import sys
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path
from typing import Any

from peel_msgs_py.cliargs import (
    ArgumentParser,
    float_list,
    int_arg,
    int_list,
    nonnegative_int,
    positive_int,
    run_main,
)

FRESH_SEED = 999_999


@lru_cache(maxsize=8)
def _tasks(source: str, n: int, seed: int, level: int | None) -> tuple[Any, ...]:
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.episode import exploratory_tasks

    return tuple(exploratory_tasks(load_sim_config(), source=source, n=n, seed=seed,
                                   level=level if source == "plant" else None))


@lru_cache(maxsize=1)
def _model_and_config() -> tuple[Any, Any]:
    import torch

    from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
    from peel_residual.config import load_residual_config

    torch.set_num_threads(1)
    return load_checkpoint(shipped_checkpoint()), load_residual_config()


def _run(args: tuple[Any, str, int | None, int]) -> dict[str, Any]:
    from peel_residual.study import run_job

    job, source, level, fresh = args
    model, cfg = _model_and_config()
    return run_job(job, _tasks(source, job.n_tasks, job.data_seed, level),
                   _tasks(source, fresh, FRESH_SEED + job.seed, level), model, cfg)


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
    p.add_argument("--workers", type=positive_int, default=1)
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    unknown = sorted(set(families) - set(STUDY_FAMILIES))
    if unknown:
        p.error(f"unknown families {unknown}; known: {', '.join(STUDY_FAMILIES)}")
    return _study(args, families, argv)


def _study(args: Any, families: list[str], argv: list[str]) -> int:
    from tqdm import tqdm

    from peel_residual.study import markdown, plan_jobs, summarise

    jobs = plan_jobs(families, args.amplitudes, args.tasks, args.draws, args.clean, args.seed)
    work = [(j, args.source, args.level, args.fresh) for j in jobs]
    args.out.mkdir(parents=True, exist_ok=True)
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
         "summary": summary, "runs": records}, indent=1) + "\n")
    (args.out / "study.md").write_text(markdown(summary, command))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("residual_study.py", main))
