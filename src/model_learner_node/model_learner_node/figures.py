"""The paper's model figures from one dataset (4.3): Fig. 9 and Fig. 10.

* **Fig. 9** -- validation RMSE per epoch of ``ours`` trained with L_MSE + kappa L_PENE (solid)
  and with L_MSE only (dashed), Eq. 23-25.
* **Fig. 10** -- ``ours`` against the MLP and CNN-LSTM baselines on the same test split: RMSE
  (Eq. 39) and Corr (Eq. 40) per force channel, and one test trajectory with the three
  one-step predictions.

Every run uses the same splits, seeds and training settings; the architecture (and for Fig. 9 the
loss) is the only difference. Model selection uses the validation split only (best-validation
epoch); the test split is evaluated once per trained model, after training, and never used to
choose anything. With several seeds the JSON holds the per-seed values and their mean.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from peel_model.checkpoint import atomic_write_bytes, atomic_write_json
from peel_model.config import ARCHS, ModelConfig
from peel_model.windows import stack_windows, trajectory_windows
from peel_msgs_py.trajectory import Trajectory

from .config import TrainConfig
from .metrics import persistence_metrics, predict_windows
from .train import dataset_hash, train_and_save

#: (name, arch, use_pene) of the trained runs.
RUNS: tuple[tuple[str, str, bool], ...] = (
    ("ours", "ours", True),
    ("ours_no_pene", "ours", False),
    ("mlp", "mlp", True),
    ("cnn-lstm", "cnn-lstm", True),
)


def _mean(xs: Sequence[float]) -> float:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(xs)) if xs else float("nan")


def run_figures(
    train: Sequence[Trajectory],
    val: Sequence[Trajectory],
    test: Sequence[Trajectory],
    out_dir: str | Path,
    *,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    seeds: Sequence[int] = (0,),
    progress: bool = True,
    device: str = "cpu",
    settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train every run of :data:`RUNS` for every seed; write PNGs + ``figures.json``."""
    out = Path(out_dir)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    results: dict[str, list] = {name: [] for name, _, _ in RUNS}
    models: dict[str, Any] = {}
    for seed in seeds:
        for name, arch, pene in RUNS:
            cfg = replace(train_cfg, seed=seed)
            res, metrics = train_and_save(
                out / "checkpoints" / f"{name}_seed{seed}", train, val, test,
                model_cfg=model_cfg.with_arch(arch), train_cfg=cfg, use_pene=pene,
                device=device, progress=progress,
            )
            results[name].append({"seed": seed, "metrics": metrics,
                                   "val_rmse": res.val_rmse_curve})
            if seed == seeds[0]:
                models[name] = res.predictor
    test_win = stack_windows(test, model_cfg.h)
    data: dict[str, Any] = {
        "dataset_hash": dataset_hash(train, val, test),
        "n_trajectories": {"train": len(train), "val": len(val), "test": len(test)},
        "n_test_samples": len(test_win),
        "seeds": list(seeds),
        "settings": {"model": model_cfg.to_json(), "train": train_cfg.to_json(),
                     **(settings or {})},
        "fig9": {
            key: {"val_rmse": [r["val_rmse"] for r in results[name]],
                  "best_val_rmse": [r["metrics"]["best_val_rmse"] for r in results[name]],
                  "test_rmse": _mean([r["metrics"]["test_rmse"]["all"] for r in results[name]])}
            for key, name in (("with_pene", "ours"), ("without_pene", "ours_no_pene"))
        },
        "fig10": {},
        "persistence": persistence_metrics(test_win),
    }
    for name, arch, pene in RUNS:
        if name == "ours_no_pene":
            continue
        per = [r["metrics"] for r in results[name]]
        data["fig10"][arch] = {
            "test_rmse": {ch: _mean([m["test_rmse"][ch] for m in per])
                          for ch in ("fx", "fz", "all")},
            "test_corr": {ch: _mean([m["test_corr"][ch] for m in per]) for ch in ("fx", "fz")},
            "per_seed": [{"seed": r["seed"], "test_rmse": r["metrics"]["test_rmse"],
                          "test_corr": r["metrics"]["test_corr"],
                          "best_epoch": r["metrics"]["best_epoch"]} for r in results[name]],
            "use_pene": pene,
        }
    ranking = sorted(ARCHS, key=lambda a: data["fig10"][a]["test_rmse"]["all"])
    data["ranking_by_test_rmse"] = ranking
    data["ours_beats_baselines"] = ranking[0] == "ours"
    _plot_fig9(data, out / "fig9_pene_ablation.png")
    _plot_fig10(data, models, test, out / "fig10_model_comparison.png")
    atomic_write_json(out / "figures.json", data)
    return data


def _save_png(fig, path: Path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def _plot_fig9(data: dict, path: Path) -> None:
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for key, style, label in (("with_pene", "-", "L_MSE + κ L_PENE"),
                              ("without_pene", "--", "L_MSE only")):
        for i, curve in enumerate(data["fig9"][key]["val_rmse"]):
            ax.plot(range(len(curve)), curve, style, color="C0" if key == "with_pene" else "C3",
                    alpha=1.0 if i == 0 else 0.5, label=label if i == 0 else None)
    ax.set_xlabel("epoch")
    ax.set_ylabel("validation RMSE (N)")
    ax.set_yscale("log")
    ax.set_title("Fig. 9: validation RMSE per epoch (ours)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    _save_png(fig, path)
    plt.close(fig)


def _plot_fig10(data: dict, models: dict, test: Sequence[Trajectory], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_bar, ax_ts) = plt.subplots(1, 2, figsize=(12, 4.2))
    chans = ("fx", "fz")
    width = 0.2
    x = np.arange(len(chans))
    for i, arch in enumerate(ARCHS):
        vals = [data["fig10"][arch]["test_rmse"][c] for c in chans]
        ax_bar.bar(x + (i - 1.5) * width, vals, width, label=arch)
    pers = [data["persistence"]["rmse"][c] for c in chans]
    ax_bar.bar(x + 1.5 * width, pers, width, color="0.7", label="F(k+1)=F(k) (reference)")
    ax_bar.set_xticks(x, ["F_RX", "F_RZ"])
    ax_bar.set_ylabel("test RMSE (N)")
    ax_bar.set_title("Fig. 10: one-step test RMSE per channel")
    ax_bar.legend(fontsize=8)
    # one test trajectory (the longest) with each model's one-step predictions of F_RX
    traj = max(test, key=len)
    win = trajectory_windows(traj, next(iter(models.values())).h)
    t = traj.t[1 : 1 + len(win)]
    ax_ts.plot(t, win.f_next[:, 0], color="k", lw=2, label="measured F_RX")
    for arch in ARCHS:
        ax_ts.plot(t, predict_windows(models[arch], win)[:, 0], lw=1, label=arch)
    ax_ts.set_xlabel("t (s)")
    ax_ts.set_ylabel("F_RX (N)")
    ax_ts.set_title("one test trajectory, one-step predictions")
    ax_ts.legend(fontsize=8)
    _save_png(fig, path)
    plt.close(fig)
