"""Calibration sweep: forces against constant speed (Table 1 magnitudes), figure + JSON.

``peel bench sim --calibrate PNG`` runs, for each constant command in ``SPEEDS`` and ``n_sets``
random parameter sets of the source, one full task and records mean F_RX / F_RZ, the stick-slip
amplitude (mean size of the sample-to-sample F_RX drops larger than 0.5 N), the prewarning rate
and the completion time of finished tasks. Writes the PNG and the JSON beside it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from peel_msgs_py.atomic import atomic_write, atomic_write_text

from .config import SimConfig
from .env import PeelEnv, sample_params
from .episode import run_episode

SPEEDS = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0)


def sweep(cfg: SimConfig, source: str = "sim", n_sets: int = 8, seed: int = 0) -> dict:
    """Per speed: means over the n_sets tasks."""
    rng = np.random.default_rng(seed)
    sets = [sample_params(cfg, rng, source) for _ in range(n_sets)]
    rows = []
    with PeelEnv(cfg, source=source, seed=seed) as env:
        for u in SPEEDS:
            fx, fz, amp, stop, tcpl = [], [], [], [], []
            for i, p in enumerate(sets):
                tr = run_episode(env, lambda h, u=u: u, seed=seed + i, params=p)
                fx.append(tr.fx.mean())
                fz.append(tr.fz.mean())
                d = np.diff(tr.fx)
                drops = -d[d < -0.5]
                amp.append(drops.mean() if drops.size else 0.0)
                stop.append(tr.outcome == "safety_stop")
                if tr.outcome == "done":
                    tcpl.append(tr.t_cpl)
            rows.append({"u_mmps": u, "mean_fx_n": float(np.mean(fx)),
                         "mean_fz_n": float(np.mean(fz)), "std_fx_n": float(np.std(fx)),
                         "std_fz_n": float(np.std(fz)),
                         "stick_slip_drop_n": float(np.mean(amp)),
                         "prewarning_rate": float(np.mean(stop)),
                         "t_cpl_done_s": float(np.mean(tcpl)) if tcpl else None})
    return {"source": source, "n_sets": n_sets, "seed": seed, "rows": rows}


def write_figure(results: list[dict], png: str | os.PathLike[str], f_prewarn: float) -> None:
    """Force against speed for each source; JSON written beside the PNG (atomic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for res, ls in zip(results, ("-", "--"), strict=False):
        u = [r["u_mmps"] for r in res["rows"]]
        src = res["source"]
        ax.errorbar(u, [r["mean_fx_n"] for r in res["rows"]], [r["std_fx_n"] for r in res["rows"]],
                    ls=ls, marker="o", capsize=2, label=f"mean F_RX ({src})")
        ax.errorbar(u, [r["mean_fz_n"] for r in res["rows"]], [r["std_fz_n"] for r in res["rows"]],
                    ls=ls, marker="s", capsize=2, label=f"mean F_RZ ({src})")
        ax.plot(u, [r["stick_slip_drop_n"] for r in res["rows"]], ls=ls, marker="^",
                label=f"stick-slip drop ({src})")
        ax2.plot(u, [r["prewarning_rate"] for r in res["rows"]], ls=ls, marker="o",
                 label=f"prewarning rate ({src})")
    ax.axhspan(9.5, 11.5, color="C0", alpha=0.1, label="Table 1 mean F_RX")
    ax.axhspan(6.0, 7.0, color="C1", alpha=0.1, label="Table 1 mean F_RZ")
    ax.axvspan(25 / 14, 25 / 7, color="grey", alpha=0.1)
    ax.set_xlabel("constant command u (mm/s)")
    ax.set_ylabel("force (N)")
    ax.set_title(f"Forces vs speed (prewarning {f_prewarn:g} N)")
    ax.legend(fontsize=7)
    ax2.set_xlabel("constant command u (mm/s)")
    ax2.set_ylabel("fraction of tasks stopped at 20 N")
    ax2.set_ylim(-0.05, 1.05)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    atomic_write(png, lambda tmp: fig.savefig(tmp, dpi=110))
    plt.close(fig)
    atomic_write_text(png.with_suffix(".json"), json.dumps(results, indent=2))
