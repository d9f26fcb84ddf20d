#!/usr/bin/env python3
"""How far can a fit on task 1's own samples lower its second-half one-step force error?

Usage: ``.venv/bin/python scripts/fast_step_ceiling.py --level 3 --seeds 1301,1302,1303``

Per seed, task 1 of ``peel experiment`` (the same substrate, task seed and planner seed) is
peeled by the shipped planner on the pretrained model, as every arm's task 1 starts. On its
one-step windows the pretrained model is then fitted to convergence (Adam, ``--iters`` steps,
``--lr``, the model's loss L_MSE + kappa L_PENE of Eq. 23-25, full batch), moving the output
layer only (``head``, as the fast step's ``fast_params: head``) or every parameter (``all``),
on three sample sets:

* ``in_sample``: every window of the task, the second half included: no fit on the task's
  samples can do better on them, a bound and not a predictor;
* ``first_half``: the windows whose target lies in the first half, scored on the second;
* ``causal``: at each control period of the second half (every 5 samples), a fit on every
  window whose target came before it, scored on the next 5 targets, the same schedule as the
  fast step (docs/experiments.md, "The fast step inside the peel") but converged and without its
  held-out check.

Prints one JSON object: per seed and fit the second-half RMS of ||F_{k+1} - f|| (both channels)
over the pretrained model's, and the mean and range over seeds. The fast step's target is
<= 0.7 (within task 1).
"""

from __future__ import annotations

import argparse
import copy
import json

import numpy as np
import torch

from model_learner_node.maml import model_loss_fn
from peel_experiments.experiment import planner_params, substrates
from peel_experiments.fast_arm import _errors
from peel_experiments.oracle import learned_planner
from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_model.windows import Windows, trajectory_windows
from peel_msgs_py.task import mppi_seed, task_seed
from peel_planner_node.config import PlannerConfig
from peel_planner_node.cost import Cost
from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv
from peel_sim_node.episode import run_episode

PERIOD = 5  # model steps per control period (0.5 s / 0.1 s)


def fit(prior: torch.nn.Module, win: Windows, which: str, iters: int, lr: float
        ) -> torch.nn.Module:
    """A copy of ``prior`` with its head (or every parameter) fitted to ``win``."""
    model = copy.deepcopy(prior)
    params = [p for p in model.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    moved = params[-2:] if which == "head" else params
    for p in moved:
        p.requires_grad_(True)
    opt, loss_fn, w = torch.optim.Adam(moved, lr=lr), model_loss_fn(model), win.to_torch()
    model.train()
    for _ in range(iters):
        opt.zero_grad()
        loss_fn(model(w.hist, w.v_next), w).backward()
        opt.step()
    model.eval()
    return model


def task1(seed: int, level: int, prior: torch.nn.Module) -> Windows:
    """Task 1 of ``peel experiment --plant level --seeds seed``, planned on ``prior``."""
    sim = load_sim_config(None)
    params = substrates(sim, seed, 1, 0, level, "stationary")[0]
    pcfg = PlannerConfig.from_params(planner_params())
    planner = learned_planner(prior, pcfg.replace(**{"mppi.seed": mppi_seed(seed, 0, 0)}),
                              Cost(pcfg.cost))
    planner.reset()
    with PeelEnv(sim, source="plant", seed=task_seed(seed, 0, 0), params=params,
                 level=level) as env:
        traj = run_episode(env, planner.plan, seed=task_seed(seed, 0, 0), params=params)
    return trajectory_windows(traj, int(prior.h))


def ratios(win: Windows, prior: torch.nn.Module, iters: int, lr: float) -> dict[str, float]:
    e0 = _errors(prior, win)
    half = len(e0) // 2
    target = np.arange(len(win)) + 1

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(e[half:] ** 2)))

    out = {"samples": len(e0) + 1, "pretrained_n": rms(e0)}
    for which in ("head", "all"):
        for name, sel in (("in_sample", np.arange(len(win))), ("first_half", np.arange(half))):
            out[f"{which}_{name}"] = rms(_errors(fit(prior, win.subset(sel), which, iters, lr),
                                                 win)) / out["pretrained_n"]
        e = e0.copy()
        for n in range(half + 1, len(e0) + 1, PERIOD):
            model = fit(prior, win.subset(np.flatnonzero(target < n)), which, iters, lr)
            now = (target >= n) & (target < n + PERIOD)
            e[now] = _errors(model, win)[now]
        out[f"{which}_causal"] = rms(e) / out["pretrained_n"]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--level", type=int, default=3)
    p.add_argument("--seeds", required=True, help="comma-separated experiment seeds")
    p.add_argument("--iters", type=int, default=400)
    p.add_argument("--lr", type=float, default=3e-3)
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    per_seed = {}
    for seed in (int(s) for s in args.seeds.split(",")):
        prior = load_checkpoint(shipped_checkpoint())
        per_seed[str(seed)] = ratios(task1(seed, args.level, prior), prior, args.iters, args.lr)
    keys = [k for k in next(iter(per_seed.values())) if k not in ("samples", "pretrained_n")]
    summary = {k: {"mean": float(np.mean([r[k] for r in per_seed.values()])),
                   "min": float(np.min([r[k] for r in per_seed.values()])),
                   "max": float(np.max([r[k] for r in per_seed.values()]))} for k in keys}
    print(json.dumps({"level": args.level, "iters": args.iters, "lr": args.lr,
                      "per_seed": per_seed, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
