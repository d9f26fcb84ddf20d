"""``peel residual``: where the forward model is wrong on recorded bags, why, and the fix.

    peel residual BAG [BAG ...] [--model CKPT] --out DIR [--force] [--holdout FRACTION]
                  [--seed S] [--params FILE] [--no-progress]

Reads the tasks of the bags (:mod:`.tasks`), runs the analysis (:mod:`.analysis`), writes
``DIR/report.json``, ``DIR/report.md``, the PNG figures and, when an effect is named, the
corrected model ``DIR/corrected.safetensors`` + ``.json`` (a checkpoint like any other, with the
terms in its JSON). Prints a JSON summary on stdout. Bad input (a bag without the /peel topics,
a truncated bag, a model whose inputs do not match the data) is a one-line error, exit 2, and
nothing is written: the output folder (:class:`~peel_msgs_py.outputs.OutputDir`) is checked
first and created only when the report is written.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import sys
from pathlib import Path
from typing import Any

from peel_model.predictor import INPUT_COLUMNS
from peel_msgs_py.cliargs import ArgumentParser, float_arg, nonnegative_int, run_main
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import OutputDir

from .params import RESIDUAL_SPECS

RESIDUAL_DOC = "docs/residual.md"
_HOLDOUT = next(s for s in RESIDUAL_SPECS if s.name == "residual.holdout")


def build_parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="peel residual",
        description="Trace the forward model's residual on recorded bags to physical effects, "
                    "add them as a compensation term and report the error before and after "
                    f"on held-out tasks ({RESIDUAL_DOC}).")
    p.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 directories with /peel topics")
    p.add_argument("--model", metavar="CKPT", default=None,
                   help="checkpoint to analyse (default: the shipped pretrained model)")
    p.add_argument("--out", metavar="DIR", type=Path, required=True, help="output directory")
    p.add_argument("--force", action="store_true",
                   help="replace an earlier 'peel residual' run in --out")
    p.add_argument("--holdout", type=float_arg(_HOLDOUT.min, _HOLDOUT.max), default=None,
                   metavar="FRACTION",
                   help="share of the tasks held out of the fit (default: residual.holdout)")
    p.add_argument("--seed", type=nonnegative_int, default=None,
                   help="seed (default: residual.seed)")
    p.add_argument("--params", metavar="FILE", default=None,
                   help="parameter file over config/ (the residual group of peel_residual; "
                        "the planner's mppi.horizon for the open-loop horizon)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def check_model_inputs(path: Path) -> dict[str, Any]:
    """The checkpoint's config, after checking that its inputs are what bags provide."""
    from peel_model.checkpoint import checkpoint_paths, read_checkpoint_config

    st, js = checkpoint_paths(path)
    if not st.is_file():
        if path.is_file():
            raise PeelError(f"--model {path}: cannot read {path} as a checkpoint (a checkpoint is "
                            f"a .safetensors file with its .json beside it; {st} does not exist)")
        raise PeelError(f"--model {path}: no such checkpoint: cannot read {st}")
    cfg = read_checkpoint_config(js)
    units = cfg.get("units") or {}
    cols = units.get("hist_columns")
    if list(cols or []) != list(INPUT_COLUMNS) or units.get("v_next") != "mm/s":
        raise PeelError(f"--model {path}: its inputs are {cols} (v_next {units.get('v_next')}), "
                        f"but the bags give {list(INPUT_COLUMNS)} and v in mm/s")
    dt = units.get("dt_s")
    if not isinstance(dt, (int, float)) or not dt > 0:
        raise PeelError(f"--model {path}: its config has no valid units.dt_s ({dt!r})")
    return cfg


def _config(args: argparse.Namespace) -> Any:
    from .config import load_residual_config

    if args.params is not None and not Path(args.params).is_file():
        raise PeelError(f"--params: no such file {args.params}")
    changes = {k: getattr(args, k) for k in ("holdout", "seed") if getattr(args, k) is not None}
    return load_residual_config(args.params, **changes)


def warn_unconverged(traces: dict[str, Any]) -> list[str]:
    """One stderr line per traced channel group whose lasso fits did not all converge."""
    lines = []
    for group, tr in traces.items():
        n = int(tr.lasso.get("unconverged_fits", 0))
        if n:
            channels = group if group == "v" else "fx, fz"
            lines.append(f"peel residual: warning: {n} lasso fit(s) on channel(s) {channels} "
                         f"did not converge (report.json: selection.{group}.lasso)")
    for line in lines:
        print(line, file=sys.stderr)
    return lines


def _save_corrected(out: Path, result: Any, model_path: Path, bags: list[str]) -> Path:
    from peel_model.checkpoint import save_checkpoint

    sha = hashlib.sha256(model_path.with_suffix(".safetensors").read_bytes()).hexdigest()
    meta = {"source": "peel residual", "base_model": str(model_path), "base_sha256": sha,
            "bags": bags, "effects": [t.to_json() for t in result.terms],
            "rmse_before": result.rmse_before, "rmse_after": result.rmse_after}
    return save_checkpoint(out / "corrected.safetensors", result.corrected, meta)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    out = OutputDir(args.out, command="peel residual", force=args.force)
    cfg = _config(args)
    import torch

    from peel_model.checkpoint import load_checkpoint, shipped_checkpoint

    from .analysis import STAGES, analyse
    from .report import write_report
    from .tasks import load_tasks

    torch.set_num_threads(1)  # small batches: one thread is fastest on a shared machine
    model_path = Path(args.model) if args.model else shipped_checkpoint()
    mcfg = check_model_inputs(model_path)
    dt = float(mcfg["units"]["dt_s"])
    model = load_checkpoint(model_path)
    tasks = load_tasks(args.bags, h=int(model.h), dt_s=dt)
    from tqdm import tqdm

    with tqdm(total=len(STAGES), desc="peel residual", unit="stage",
              disable=args.no_progress) as bar:
        def tick(stage: str) -> None:
            bar.set_postfix_str(stage)
            bar.update(1)

        result = analyse(tasks, model, cfg, dt_s=dt, progress=tick)
    warn_unconverged(result.traces)
    with out as out_dir:  # created only now: bad input above leaves nothing behind
        corrected = None
        if result.corrected is not None:
            corrected = _save_corrected(out_dir, result, model_path, [str(b) for b in args.bags])
        info = {"command": "peel residual " + " ".join(shlex.quote(a) for a in argv),
                "bags": [str(b) for b in args.bags], "dt_s": dt,
                "model": {"path": str(model_path), "arch": model.arch, "h": int(model.h),
                          "terms_before": [t.to_json() for t in getattr(model, "terms", ())]},
                "corrected_model": str(corrected) if corrected else None}
        rep = write_report(out_dir, result, tasks, cfg, info)
    print(json.dumps({"out": str(args.out), "corrected_model": rep["corrected_model"],
                      "effects": [{k: e[k] for k in ("key", "channel", "expression",
                                                     "explained_variance")}
                                  for e in rep["effects"]],
                      "rmse_before": rep["rmse_before"], "rmse_after": rep["rmse_after"],
                      "verdicts": {ch: v["verdict"] for ch, v in rep["verdicts"].items()}},
                     indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_main("peel residual", main))
