"""The paper's OL-MPPI arm in two sets of ``peel experiment`` cells, cell by cell (docs/planner.md,
"The slowdown on the measured force" and "The bridges' slowdown zone"): stops, peels >= 18 N,
mean J and T_cpl and their change, J / T_cpl paired over the peels both finished, and how often
Eq. M5 (commands) and Eq. M6 (peels, samples) acted.

    python scripts/slowdown_compare.py BASE_DIR OTHER_DIR     # each holds L<L>_<S>/results.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

ARM = "ol-mppi"


def tasks(res: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """Per seed, the arm's task records."""
    return {seed: runs[ARM]["tasks"] for seed, runs in res["runs"].items()}


def counts(per_seed: dict[str, list[dict[str, Any]]]) -> dict[str, float]:
    """Peels, stops, peels >= 18 N, mean J, mean T_cpl, Eq. M5 commands, Eq. M6 peels and
    samples of one cell."""
    recs = [t for ts in per_seed.values() for t in ts]
    zone = [(t.get("slowdown") or {}).get("samples_slowed", 0) for t in recs]
    return {"peels": len(recs), "stops": sum(t["outcome"] == "safety_stop" for t in recs),
            "over_18n": sum(max(t["max_abs_fx"], t["max_abs_fz"]) >= 18.0 for t in recs),
            "J": float(np.mean([t["cost"] for t in recs])),
            "t_cpl_s": float(np.mean([t["t_cpl"] for t in recs])),
            "slowed": sum((t.get("planner_guard") or {}).get("commands_slowed", 0) for t in recs),
            "zone_peels": sum(n > 0 for n in zone), "zone_samples": sum(zone)}


def paired(a: dict[str, list[dict[str, Any]]], b: dict[str, list[dict[str, Any]]]
           ) -> dict[str, float]:
    """Mean relative change of J and T_cpl over the substrates both runs finished."""
    pairs = [(x, y) for seed in b for x, y in zip(a[seed], b[seed], strict=True)
             if x["outcome"] == y["outcome"] == "done"]
    return {"n": len(pairs),
            "dJ": float(np.mean([y["cost"] / x["cost"] - 1 for x, y in pairs])),
            "dT": float(np.mean([y["t_cpl"] / x["t_cpl"] - 1 for x, y in pairs]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base", type=Path)
    ap.add_argument("other", type=Path)
    args = ap.parse_args()
    cells = {}
    for folder in sorted(p for p in args.other.glob("L*_*") if (p / "results.json").is_file()):
        base = args.base / folder.name / "results.json"
        if not base.is_file():
            continue
        a = tasks(json.loads(base.read_text()))
        b = tasks(json.loads((folder / "results.json").read_text()))
        ca, cb = counts(a), counts(b)
        change = {k: cb[k] / ca[k] - 1 for k in ("J", "t_cpl_s")}
        cells[folder.name] = {"base": ca, "other": cb, "mean_change": change,
                              "paired": paired(a, b)}
    total = {k: {m: sum(c[k][m] for c in cells.values()) for m in ("peels", "stops", "over_18n")}
             for k in ("base", "other")}
    print(json.dumps({"arm": ARM, "cells": cells, "total": total}, indent=1))


if __name__ == "__main__":
    main()
