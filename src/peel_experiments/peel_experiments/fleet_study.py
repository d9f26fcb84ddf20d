"""``peel experiment fleet``: does one learner over K cells close the headroom sooner (docs/fleet.md)?

Per seed s of ``seeds``:

* ``peel fleet --cells K --tasks T --plant plant --seed s`` (real processes, ``OUT/fleet_s<s>``):
  cell c peels T substrates of seed ``cell_seed(s, c)``; every task records J and the version
  of the model it started with, i.e. how many peels of the whole fleet that model had learned;
* the same substrates in-process (:func:`peel_experiments.experiment.run_experiment`, which
  peels task k of a seed exactly as the graph does, docs/graph.md): Baseline 1 and the oracle
  for the headroom, and OL-MPPI learning alone on the seed ("alone": the cell by itself),
  K * T tasks for cell 0 (one cell, the fleet's number of peels) and T for the others.

Fraction of headroom closed at a group of peels (docs/experiments.md, one task, no window):
``sum(J_B1 - J_m) / sum(J_B1 - J_oracle)`` over the group, pooled over seeds and cells; the
groups are a cell's own task index k and the number of peels the planning model had learned.
Writes ``summary.json``, ``summary.md`` and ``headroom.png`` into ``OUT``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from peel_msgs_py.errors import PeelError

from .experiment import run_experiment
from .experiment_config import ORACLE, ExperimentConfig

#: target (docs/fleet.md): with 3 cells, each cell at >= 90 % of the headroom by its own task 2
TARGET_CLOSED, TARGET_TASK = 0.90, 2
_KEYS = ("seed", "cell", "task", "learned", "J", "J_b1", "J_oracle")


def fleet_command(cells: int, tasks: int, seed: int, out: Path) -> list[str]:
    """The ``peel fleet`` run of one seed (every cell on the plant, config's level)."""
    return [sys.executable, "-m", "peel_bringup.cli", "fleet", "--cells", str(cells), "--tasks",
            str(tasks), "--plant", "plant", "--seed", str(seed), "--out", str(out), "--force"]


def run_fleet(cells: int, tasks: int, seed: int, out: Path) -> dict[str, Any]:
    """``peel fleet`` for ``seed`` into ``out`` (its output in ``out.log``), or the summary of an
    earlier whole run there with the same cells and tasks."""
    old = _read_summary(out / "summary.json")
    if old is not None and old.get("status") == 0 and old.get("tasks") == tasks \
            and len(old.get("cells", {})) == cells:
        return old
    log = out.with_suffix(".log")
    with log.open("w") as fh:
        rc = subprocess.run(fleet_command(cells, tasks, seed, out), stdout=fh,
                            stderr=subprocess.STDOUT, check=False).returncode
    summary = _read_summary(out / "summary.json")
    if rc != 0 or summary is None:
        raise PeelError(f"peel fleet --seed {seed} exited {rc}; its output: {log}")
    return summary


def _read_summary(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def run_alone(cfg: ExperimentConfig, seeds: Sequence[int], tasks: int, out: Path, *,
              checkpoint: str, command: str) -> dict[str, Any]:
    """OL-MPPI alone, Baseline 1 and the oracle on ``seeds`` (reused when ``out`` holds them)."""
    old = _read_summary(out / "results.json")
    if old is not None and old.get("tasks") == tasks and old.get("seeds") == list(seeds):
        return old
    acfg = replace(cfg, seeds=tuple(seeds), tasks=tasks, methods=("ol-mppi", "baseline1"),
                   oracle=True, save_model=False)
    return run_experiment(acfg, checkpoint=checkpoint, out=out, command=command)


def _costs(results: Mapping[str, Any], seed: int, method: str) -> list[float]:
    return [float(r["cost"]) for r in results["runs"][str(seed)][method]["tasks"]]


def peel_rows(fleets: Mapping[int, Mapping[str, Any]], alone: Iterable[Mapping[str, Any]]
              ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """One row per fleet peel and per lone peel: J, the model's learned peels, J_B1, J_oracle."""
    ref: dict[int, dict[str, list[float]]] = {}
    for res in alone:
        for s in res["seeds"]:
            ref[int(s)] = {m: _costs(res, s, m) for m in ("ol-mppi", "baseline1", ORACLE)}
    fleet_rows, alone_rows = [], []
    for seed, summary in fleets.items():
        for name, cell in summary["cells"].items():
            r = ref[int(cell["seed"])]
            for rec in cell["results"]:
                k = int(rec["task"])
                fleet_rows.append(dict(zip(_KEYS, (seed, name, k, int(rec["model_version"]),
                                                   float(rec["J"]), r["baseline1"][k - 1],
                                                   r[ORACLE][k - 1]), strict=True)))
            for k, j in enumerate(r["ol-mppi"], start=1):
                alone_rows.append(dict(zip(_KEYS, (seed, name, k, k - 1, j, r["baseline1"][k - 1],
                                                   r[ORACLE][k - 1]), strict=True)))
    return fleet_rows, alone_rows


def closed(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Pooled fraction of the headroom closed over ``rows`` (module docstring), with its parts."""
    gain = sum(r["J_b1"] - r["J"] for r in rows)
    room = sum(r["J_b1"] - r["J_oracle"] for r in rows)
    return {"closed": gain / room if abs(room) > 1e-9 else None, "peels": len(rows),
            "headroom_per_peel": room / len(rows) if rows else None,
            "J_mean": sum(r["J"] for r in rows) / len(rows) if rows else None}


def by(rows: Sequence[Mapping[str, Any]], key: str) -> dict[str, dict[str, Any]]:
    """:func:`closed` per value of ``key`` (``task`` or ``learned``)."""
    groups: dict[int, list[Mapping[str, Any]]] = {}
    for r in rows:
        groups.setdefault(int(r[key]), []).append(r)
    return {str(k): closed(v) for k, v in sorted(groups.items())}


def seed_interval(rows: Sequence[Mapping[str, Any]], resamples: int = 10_000,
                  seed: int = 0) -> list[float] | None:
    """95 % bootstrap interval of :func:`closed` over the substrate sequences of ``rows`` (a
    cell of a seed; each sequence's peels drawn together); None with fewer than two."""
    groups = sorted({(r["seed"], r["cell"]) for r in rows})
    if len(groups) < 2:
        return None
    of = [[r for r in rows if (r["seed"], r["cell"]) == g] for g in groups]
    gain = np.array([sum(r["J_b1"] - r["J"] for r in g) for g in of])
    room = np.array([sum(r["J_b1"] - r["J_oracle"] for r in g) for g in of])
    pick = np.random.default_rng(seed).integers(0, len(groups), (resamples, len(groups)))
    ratios = gain[pick].sum(axis=1) / room[pick].sum(axis=1)
    return [float(x) for x in np.percentile(ratios, [2.5, 97.5])]


def analyse(fleet_rows: list[dict[str, Any]], alone_rows: list[dict[str, Any]], cells: int,
            tasks: int) -> dict[str, Any]:
    """The study's figures from its rows (module docstring)."""
    one = [r for r in alone_rows if r["cell"] == "/cell_0"]
    same = [r for r in alone_rows if r["task"] <= tasks]  # every fleet cell by itself
    per_cell = {}
    for name in sorted({r["cell"] for r in fleet_rows}):
        mine = [r for r in fleet_rows if r["cell"] == name]
        per_cell[name] = {"fleet": by(mine, "task"),
                          "alone": by([r for r in same if r["cell"] == name], "task")}
    at = [v["fleet"].get(str(TARGET_TASK), {}).get("closed") for v in per_cell.values()]
    return {
        "one_cell": {"by_task": by(one, "task")},
        "fleet": {"by_task": by(fleet_rows, "task"), "by_learned": by(fleet_rows, "learned")},
        "alone_same_cells": {"by_task": by(same, "task"), "interval_by_task": {
            str(k): seed_interval([r for r in same if r["task"] == k]) for k in range(1, tasks + 1)}},
        "per_cell": per_cell,
        "target": {"closed": TARGET_CLOSED, "task": TARGET_TASK, "cells": cells,
                   "per_cell_closed": at,
                   "met": bool(at) and all(x is not None and x >= TARGET_CLOSED for x in at)},
        "fleet_minus_alone_J": _paired(fleet_rows, same),
        "same_model_max_abs_dJ": _same_model(fleet_rows, same),
    }


def _same_model(fleet_rows: Sequence[Mapping[str, Any]], alone_rows: Sequence[Mapping[str, Any]]
                ) -> dict[str, Any]:
    """The check that the in-process peels are the fleet's: where a fleet peel planned with a
    model that had learned exactly the peels the lone run's had (task 1 on the pretrained model;
    cell 0's task 2 on the update of its own task 1), the two J agree (max |difference|)."""
    alone = {(r["seed"], r["cell"], r["task"]): r for r in alone_rows}
    d = [abs(r["J"] - alone[(r["seed"], r["cell"], r["task"])]["J"]) for r in fleet_rows
         if r["learned"] == 0 or (r["cell"] == "/cell_0" and r["task"] == 2 and r["learned"] == 1)]
    return {"max": max(d) if d else None, "peels": len(d)}


def _paired(fleet_rows: Sequence[Mapping[str, Any]], alone_rows: Sequence[Mapping[str, Any]]
            ) -> dict[str, Any]:
    """Mean J(fleet) - J(alone) per own task over the same substrates (negative: pooling helps),
    with its standard error over the peels (None for one peel) and how many the fleet did better."""
    alone = {(r["seed"], r["cell"], r["task"]): r["J"] for r in alone_rows}
    out: dict[str, Any] = {}
    for k in sorted({r["task"] for r in fleet_rows}):
        d = np.array([r["J"] - alone[(r["seed"], r["cell"], k)] for r in fleet_rows
                      if r["task"] == k])
        se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else None
        out[str(k)] = {"mean": float(d.mean()), "se": se, "n": int(d.size),
                       "better": int((d < 0).sum())}
    return out


def run_fleet_study(cfg: ExperimentConfig, *, cells: int, tasks: int, seeds: Sequence[int],
                    out: Path, checkpoint: str, command: str = "") -> dict[str, Any]:
    """Every seed's fleet run and lone runs, then ``summary.{json,md}`` and ``headroom.png``."""
    from tqdm import tqdm

    from . import report as rp

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fleets = {s: run_fleet(cells, tasks, s, out / f"fleet_s{s}")
              for s in tqdm(seeds, desc="peel fleet", unit="run")}
    # each cell's seed as the fleet drew it (peel_bringup.fleet.cell_seed)
    others = [int(cell["seed"]) for s in seeds for cell in list(fleets[s]["cells"].values())[1:]]
    alone = [run_alone(cfg, seeds, cells * tasks, out / "alone_cell0", checkpoint=checkpoint,
                       command=f"{command} [cell 0 alone]")]
    if others:
        alone.append(run_alone(cfg, others, tasks, out / "alone_cells", checkpoint=checkpoint,
                               command=f"{command} [cells 1-{cells - 1} alone]"))
    fleet_rows, alone_rows = peel_rows(fleets, alone)
    summary = {"command": command, "cells": cells, "tasks": tasks, "seeds": list(seeds),
               "plant": alone[0]["plant"], "checkpoint": checkpoint,
               **analyse(fleet_rows, alone_rows, cells, tasks),
               "fleet_peels": fleet_rows, "alone_peels": alone_rows}
    rp.write_json(out / "summary.json", summary)
    rp.write_text(out / "summary.md", summary_markdown(summary))
    plot_closed(summary, out / "headroom.png")
    summary["files"] = {"json": str(out / "summary.json"), "md": str(out / "summary.md"),
                        "png": str(out / "headroom.png")}
    return summary


def _f(x: float | None, fmt: str = ".2f") -> str:
    return "–" if x is None else format(x, fmt)


def _interval(x: Sequence[float] | None) -> str:
    return "" if x is None else f" [{x[0]:.2f}, {x[1]:.2f}]"


def summary_markdown(s: Mapping[str, Any]) -> str:
    """The study's report (its figures are all in summary.json)."""
    k, t = s["cells"], s["tasks"]
    lines = [f"# {k} cells, one learner, against one cell (plant level {s['plant']['level']})", "",
             f"`{s['command']}`", "",
             f"Seeds {', '.join(map(str, s['seeds']))}: {k} cells x {t} tasks per seed against one "
             f"cell x {k * t} tasks (the same number of peels). Fraction of headroom closed = "
             "sum(J_B1 - J) / sum(J_B1 - J_oracle) over the peels of a row, pooled over seeds "
             "and cells.", "",
             "| own task | one cell | fleet, every cell | each cell alone (same substrates) [95 %] | "
             "fleet - alone, mean J ± se (fleet better) |", "|---|---|---|---|---|"]
    for task in range(1, t + 1):
        key = str(task)
        d = s["fleet_minus_alone_J"][key]
        lines.append(f"| {task} | {_f(s['one_cell']['by_task'][key]['closed'])} | "
                     f"{_f(s['fleet']['by_task'][key]['closed'])} | "
                     f"{_f(s['alone_same_cells']['by_task'][key]['closed'])}"
                     f"{_interval(s['alone_same_cells']['interval_by_task'].get(key))} | "
                     f"{d['mean']:+.2f} ± {_f(d['se'])} ({d['better']} of {d['n']}) |")
    lines += ["", "| peels the model had learned | one cell | fleet |", "|---|---|---|"]
    learned = sorted({int(x) for x in s["fleet"]["by_learned"]}
                     | {int(x) - 1 for x in s["one_cell"]["by_task"]})
    for n in learned:
        one = s["one_cell"]["by_task"].get(str(n + 1), {})
        fl = s["fleet"]["by_learned"].get(str(n), {})
        lines.append(f"| {n} | {_f(one.get('closed'))} ({one.get('peels', 0)}) | "
                     f"{_f(fl.get('closed'))} ({fl.get('peels', 0)}) |")
    tg = s["target"]
    cells = ", ".join(f"{c} {_f(v['fleet'].get(str(tg['task']), {}).get('closed'))}"
                      for c, v in s["per_cell"].items())
    lines += ["", "(peels pooled per row in brackets)", "",
              f"Target: every cell >= {tg['closed']:.0%} of the headroom by its own task "
              f"{tg['task']}: per cell {cells}: **{'met' if tg['met'] else 'not met'}**.", ""]
    return "\n".join(lines)


def plot_closed(s: Mapping[str, Any], path: Path) -> Path:
    """Fraction closed against a cell's own task and against the peels the model had learned."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, series, xlabel in (
            (a, (("one cell", s["one_cell"]["by_task"], 0), ("fleet", s["fleet"]["by_task"], 0),
                 ("each cell alone", s["alone_same_cells"]["by_task"], 0)), "cell's own task"),
            (b, (("one cell", s["one_cell"]["by_task"], -1),
                 ("fleet", s["fleet"]["by_learned"], 0)), "peels the planning model had learned")):
        for label, table, shift in series:
            xs = [int(x) + shift for x in table if table[x]["closed"] is not None]
            ys = [table[x]["closed"] for x in table if table[x]["closed"] is not None]
            ax.plot(xs, ys, marker="o", label=label)
        ax.axhline(1.0, color="grey", lw=0.8, ls=":")
        ax.axhline(TARGET_CLOSED, color="tab:red", lw=0.8, ls="--")
        ax.set_xlabel(xlabel)
        ax.legend(fontsize=8)
    a.set_ylabel("fraction of headroom closed (pooled)")
    fig.suptitle(f"{s['cells']} cells x {s['tasks']} tasks vs one cell, seeds "
                 f"{', '.join(map(str, s['seeds']))}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
