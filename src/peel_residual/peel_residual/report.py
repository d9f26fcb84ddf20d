"""``report.json`` and ``report.md`` of ``peel residual`` (with the PNG figures beside them).

report.json holds at least: ``rmse_before`` / ``rmse_after`` (per channel ``fx``, ``fz``, ``v``
and mode ``one_step`` / ``open_loop``, held-out tasks), ``effects`` (each with ``name``,
``channel``, ``expression``, ``coefficients`` (+ standard errors and intervals) and
``explained_variance``), ``unexplained`` (what structure remains, with its evidence),
``holdout`` (which tasks), plus the rejected candidates, the settings and the figure paths.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from peel_model.checkpoint import atomic_write_json
from peel_model.effect_terms import FORCE_CHANNELS, VELOCITY_CHANNEL, Term
from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.trajectory import Trajectory

from . import figures as F
from .analysis import OPEN_LOOP, Result
from .config import ResidualConfig
from .trace import Finding

CHANNELS = (*FORCE_CHANNELS, VELOCITY_CHANNEL)


def _task_ref(tasks: list[Trajectory], i: int) -> dict[str, Any]:
    meta = tasks[i].meta
    return {"index": i, "bag": meta.get("bag"), "bag_task": meta.get("bag_task"),
            "task_index": meta.get("task_index"), "samples": len(tasks[i]),
            "outcome": tasks[i].outcome}


def _findings(result: Result) -> list[Finding]:
    return [f for tr in result.traces.values() for f in tr.findings]


def effect_figures(out: Path, result: Result, dt_s: float) -> dict[tuple[str, str], str]:
    """One evidence figure per named term: the residual its fit was made on (one step ahead, or
    open loop for the output-error fit) against the term's variable, with the term's
    contribution; returns ``{(key, channel): file name}``."""
    files: dict[tuple[str, str], str] = {}
    for group, tr in result.traces.items():
        plot = result.plots["traces"].get(group)
        for f in tr.findings:
            if plot is None:
                continue
            partial, contrib, s = _evidence(result, group, plot, tr.findings, f)
            spec = f.candidate.spec
            mode = "open loop" if group == OPEN_LOOP else "one step"
            name = f"effect_{f.channel}_{F.safe_name(f.candidate.key)}.png"
            F.effect_figure(out / name, f"{spec.label} on {f.channel}: {_expression(f)} "
                            f"(fitted {mode}; held-out share {f.share:.1%})",
                            F.xlabel(spec.variable), F.UNITS[f.channel],
                            F.variable_values(spec.variable, s, f.channel, dt_s), partial,
                            contrib)
            files[(f.candidate.key, f.channel)] = name
    return files


def _evidence(result: Result, group: str, plot: dict[str, Any], findings: list[Finding],
              f: Finding) -> tuple[np.ndarray, np.ndarray, Any]:
    """(the partial residual -- the residual less the group's other terms --, the term's
    contribution, the rows' samples) of finding ``f`` of trace ``group``."""
    others = [g for g in findings if g is not f]
    if f.channel in FORCE_CHANNELS:
        i = FORCE_CHANNELS.index(f.channel)
        s = plot["steps"] if group == OPEN_LOOP else result.plots["fit"]
        n = len(s)

        def own(key: tuple[str, str]) -> np.ndarray:
            return plot["cols"][key][i * n:(i + 1) * n] * plot["rms"][i]

        y = plot["y"][:, i]
        partial = y - sum((own((g.candidate.key, g.channel)) @ g.coef for g in others),
                          np.zeros_like(y))
        return partial, own((f.candidate.key, f.channel)) @ f.coef, s
    s = result.plots["fit"].subset(plot["ok"])
    partial = plot["y"] - sum((plot["cols"][(g.candidate.key, g.channel)] @ g.coef
                               for g in others), np.zeros_like(plot["y"]))
    return partial, plot["cols"][(f.candidate.key, f.channel)] @ f.coef, s


def _expression(f: Finding) -> str:
    return Term(f.candidate, f.channel, tuple(float(c) for c in f.coef)).expression


def _effect_json(f: Finding, group: str, shares: dict[tuple[str, str], Any],
                 figures: dict[str, Any], info: dict[str, Any]) -> dict[str, Any]:
    """One named term of ``effects`` (module docstring); ``fit`` says where it was fitted."""
    d = f.to_json()
    d["fit"] = "open_loop" if group == OPEN_LOOP else "one_step"
    d["expression"] = _expression(f)
    d["heldout_share_of_mse_removed"] = {k: shares.get((f.candidate.key, f.channel), {})
                                         .get(k) for k in ("one_step", "open_loop")}
    d["figure"] = figures["effects"].get((f.candidate.key, f.channel))
    if f.candidate.family == "actuator_lag" and 0 < f.coef[0] < 1:
        d["time_constant_s"] = -info["dt_s"] / math.log(f.coef[0])
    return d


def build_json(result: Result, tasks: list[Trajectory], cfg: ResidualConfig,
               info: dict[str, Any], figures: dict[str, Any]) -> dict[str, Any]:
    """The report as a JSON-able dict (module docstring)."""
    shares = {(d["key"], d["channel"]): d for d in result.shares}
    effects = []
    for group, tr in result.traces.items():
        for f in tr.findings:
            effects.append(_effect_json(f, group, shares, figures, info))
    unexplained = []
    for st in result.structure:
        d = st.to_json()
        d["figure"] = figures["remains"].get(st.channel)
        unexplained.append(d)
    for ch, d in result.drift.items():
        unexplained.append({"channel": ch, "mode": "open_loop_drift", **d,
                            "horizon_s": cfg.horizon_steps * info["dt_s"]})
    for ch, d in result.task_drift.items():
        unexplained.append({"channel": ch, "mode": "drift_across_tasks", "variable": "task_order",
                            **d})
    return {
        "format": "peel-residual-report/1",
        **info,
        "tasks": len(tasks),
        "holdout": {"fraction": cfg.holdout, "seed": cfg.seed,
                    "tasks": [_task_ref(tasks, i) for i in result.holdout_tasks],
                    "fit_tasks": [_task_ref(tasks, i) for i in result.fit_tasks]},
        "rmse_before": result.rmse_before, "rmse_after": result.rmse_after,
        "rmse_by_horizon_step": {"before": result.by_step_before, "after": result.by_step_after},
        "effects": effects,
        "no_effect_claimed": not effects,
        "rejected": [f.to_json() for tr in result.traces.values() for f in tr.rejected],
        "selection": {g: {"lasso": tr.lasso, "best_single_candidates": tr.single,
                          "rows": tr.n_rows, "tasks": tr.n_tasks}
                      for g, tr in result.traces.items()},
        "unexplained": unexplained,
        "verdicts": verdicts(effects, unexplained),
        "samples": result.samples,
        "settings": {"holdout": cfg.holdout, "seed": cfg.seed, "folds": cfg.folds,
                     "horizon_steps": cfg.horizon_steps, "stride": cfg.stride,
                     "min_explained": cfg.min_explained, "ci_level": cfg.ci_level,
                     "bootstrap": cfg.bootstrap, "min_structure": cfg.min_structure,
                     "drift_alpha": cfg.drift_alpha, "open_loop_fit": cfg.open_loop_fit,
                     "open_loop_fit_steps": cfg.open_loop_fit_steps or cfg.horizon_steps,
                     "open_loop_fit_stride": cfg.open_loop_fit_stride,
                     "heldout_alpha": cfg.heldout_alpha,
                     "candidates": [c.key for c in cfg.candidates]},
        "figures": {"rmse": figures["rmse"], "open_loop_error": figures["horizon"]},
    }


def verdicts(effects: list[dict[str, Any]], unexplained: list[dict[str, Any]]
             ) -> dict[str, dict[str, Any]]:
    """Per force channel: what was named and what structure remains, and where (which
    variable); ``no structure left`` only when no check finds any."""
    out = {}
    for ch in FORCE_CHANNELS:
        named = [e["key"] for e in effects if e["channel"] == ch]
        remains = []
        for u in unexplained:
            if u["channel"] != ch:
                continue
            if u["mode"] == "one_step" and u["remains"]:
                remains.append({"kind": "one_step_structure",
                                "variables": list(u["importance"]), "heldout_r2": u["heldout_r2"]})
            elif u["mode"] == "open_loop_drift" and u["drift"]:
                remains.append({"kind": "open_loop_drift", "variables": ["horizon_step"],
                                "mean_n": u["mean_n"], "se_n": u["se_n"]})
            elif u["mode"] == "drift_across_tasks" and u["drift"]:
                remains.append({"kind": "drift_across_tasks", "variables": ["task_order"],
                                "slope_n_per_task": u["slope_n_per_task"], "p": u["p"]})
        verdict = ("named" if named else "unexplained") if remains else \
            ("named" if named else "no structure left")
        out[ch] = {"verdict": verdict, "named": named, "remains": remains}
    return out


def _fmt(x: float | None, nd: int = 3) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{nd}f}"


def _ratio(a: float | None, b: float | None) -> str:
    return "–" if not a or b is None else f"{b / a:.2f}"


def _md_errors(rep: dict[str, Any]) -> list[str]:
    """The before/after table."""
    L: list[str] = []
    L += ["## Error before and after (held-out tasks)", "",
          "| channel | mode | RMSE before | RMSE after | after / before |", "|---|---|---|---|---|"]
    for ch in CHANNELS:
        for mode in ("one_step", "open_loop"):
            b = rep["rmse_before"].get(ch, {}).get(mode)
            a = rep["rmse_after"].get(ch, {}).get(mode)
            unit = F.UNITS[ch]
            L.append(f"| {ch} | {mode.replace('_', ' ')} | {_fmt(b)} {unit} | {_fmt(a)} {unit} | "
                     f"{_ratio(b, a)} |")
    L += ["", "`v`: the robot's speed over the next sample predicted from the command; before = "
          "Eq. 2's mean v = u that the planner assumes.", "", "![rmse](rmse.png)",
          "![open loop](open_loop_error.png)"]
    return L


def _md_effects(rep: dict[str, Any]) -> list[str]:
    """The named effects, or why none is claimed; the rejected candidates."""
    L: list[str] = []
    L += ["", "## Effects named", ""]
    if not rep["effects"]:
        best = [c for g in rep["selection"].values() for c in g["best_single_candidates"]]
        best = sorted(best, key=lambda d: -d["explained_variance"])[:3]
        L.append("**No effect is claimed**: no candidate explains a significant share of the "
                 "held-out residual (threshold "
                 f"{rep['settings']['min_explained']:.0%}, coefficients at "
                 f"{rep['settings']['ci_level']:.0%}). Largest single candidates, held-out "
                 "one-step share: " + ", ".join(
                     f"{d['key']} on {d['channel']} {d['explained_variance']:.1%}" for d in best)
                 + ".")
    else:
        L += ["| effect | channel | fitted | term | coefficients ± SE | held-out share one step | "
              "open loop | figure |", "|---|---|---|---|---|---|---|---|"]
        for e in rep["effects"]:
            co = ", ".join(f"{c:.4g} ± {s:.2g}" for c, s in
                           zip(e["coefficients"], e["coefficient_std"], strict=True))
            ol = e.get("explained_variance_open_loop")
            tc = (f" (time constant {e['time_constant_s']:.3f} s)"
                  if "time_constant_s" in e else "")
            fit = e["fit"].replace("_", " ")
            L.append(f"| {e['label']} (`{e['key']}`) | {e['channel']} | {fit} "
                     f"| `{e['expression']}`{tc} "
                     f"| {co} | {e['explained_variance']:.1%} | "
                     f"{'–' if ol is None else f'{ol:.1%}'} | [png]({e['figure']}) |")
        L += ["", "Meaning of each: " + "; ".join(
            f"**{e['label']}**: {e['meaning']}" for e in rep["effects"]) + "."]
    if rep["rejected"]:
        L += ["", "Considered and not named: " + "; ".join(
            f"{r['key']} on {r['channel']} ({r['reason']})" for r in rep["rejected"]) + "."]
    return L


def _md_remains(rep: dict[str, Any]) -> list[str]:
    """What remains after the correction."""
    L: list[str] = []
    L += ["", "## What remains", ""]
    for ch, v in rep["verdicts"].items():
        where = "; ".join(f"{r['kind'].replace('_', ' ')} ({', '.join(r['variables'])})"
                          for r in v["remains"])
        L.append(f"* **{ch}: {v['verdict']}**" + (f", named {', '.join(v['named'])}"
                                                  if v["named"] else "")
                 + (f"; structure remains: {where}" if where else "") + ".")
    L.append("")
    for u in rep["unexplained"]:
        if u["mode"] == "one_step":
            if u["remains"]:
                imp = ", ".join(f"{k} ({v:.2f})" for k, v in u["importance"].items())
                L.append(f"* **{u['channel']}, one step: structure remains that no candidate "
                         f"explains**: a gradient-boosted regressor on the sample's variables "
                         f"explains {u['heldout_r2']:.1%} of the held-out residual after the "
                         f"correction; it leans on {imp} (permutation importance). "
                         f"[png]({u['figure']})")
            else:
                L.append(f"* {u['channel']}, one step: no structure left that the state "
                         f"variables predict (flexible regressor held-out R^2 "
                         f"{u['heldout_r2']:.2f}).")
        elif u["mode"] == "drift_across_tasks":
            if u["slope_n_per_task"] is None:
                continue
            what = ("**a drift across tasks**: the offset changes from one task to the next"
                    if u["drift"] else "no significant drift across tasks")
            L.append(f"* {u['channel']}, across tasks: the force at each task's first sample "
                     f"(blade at rest at C; the other channel's as covariate) against the task "
                     f"order, slope {u['slope_n_per_task']:+.3f} ± {u['se']:.3f} N per "
                     f"task (p = {u['p']:.2g}, {u['tasks']} tasks): {what}.")
        else:
            what = ("a systematic open-loop drift of the model" if u["drift"]
                    else "no significant drift")
            L.append(f"* {u['channel']}, open loop: mean residual at the horizon end "
                     f"{u['mean_n']:+.2f} ± {u['se_n']:.2f} N (SE over {u['tasks']} held-out "
                     f"tasks): {what}.")
    return L

def build_markdown(rep: dict[str, Any]) -> str:
    """report.md from the JSON dict."""
    L = [f"# peel residual: {rep['model']['path']}", "",
         f"Command: `{rep.get('command', '')}`", "",
         f"{rep['tasks']} tasks from {len(rep['bags'])} bag(s); "
         f"{len(rep['holdout']['tasks'])} held out (seed {rep['holdout']['seed']}), fitted on "
         f"{len(rep['holdout']['fit_tasks'])}. Open loop: {rep['settings']['horizon_steps']} "
         f"model steps ({rep['settings']['horizon_steps'] * rep['dt_s']:.1f} s, the planner's "
         "horizon), the model fed its own forces and the measured speeds.", ""]
    L += _md_errors(rep) + _md_effects(rep) + _md_remains(rep)
    cm = rep.get("corrected_model")
    L += ["", "## Corrected model", "",
          f"`{cm}` (f_theta unchanged, the named terms in its JSON; loads in the planner, the "
          "learner, `peel graph` and `peel experiment` like any checkpoint)." if cm else
          "None written: no effect was named.", ""]
    return "\n".join(L)


def write_report(out: Path, result: Result, tasks: list[Trajectory], cfg: ResidualConfig,
                 info: dict[str, Any]) -> dict[str, Any]:
    """Figures, report.json and report.md into ``out``; returns the JSON dict."""
    out.mkdir(parents=True, exist_ok=True)
    figs: dict[str, Any] = {"effects": effect_figures(out, result, info["dt_s"]),
                            "remains": {}, "rmse": "rmse.png", "horizon": "open_loop_error.png"}
    F.rmse_figure(out / "rmse.png", result.rmse_before, result.rmse_after)
    F.horizon_figure(out / "open_loop_error.png", result.by_step_before, result.by_step_after,
                     info["dt_s"])
    fit = result.plots["fit"]
    for i, st in enumerate(result.structure):
        if st.remains and st.importance:
            name = f"remains_{st.channel}.png"
            F.remains_figure(out / name, st.channel, fit, result.plots["y_after"][:, i],
                             next(iter(st.importance)), st.heldout_r2)
            figs["remains"][st.channel] = name
    rep = build_json(result, tasks, cfg, info, figs)
    atomic_write_json(out / "report.json", rep)
    atomic_write_text(out / "report.md", build_markdown(rep))
    return rep
