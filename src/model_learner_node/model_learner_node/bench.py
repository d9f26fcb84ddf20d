"""``peel bench model --json``: training throughput and inference latency of each architecture.

For ``ours``, ``mlp`` and ``cnn-lstm`` (default config, CPU unless ``--device``): training
samples per second (replay sampling + forward + L_MSE + kappa L_PENE + backward + Adam step, batch
of ``train.batch_size`` slices of synthetic trajectories), and the median latency of ``predict``
for batch 1 and batch 1000 under ``torch.no_grad`` (the planner calls it with N = 50..1000).
Prints one JSON object keyed by architecture. Numbers depend on the machine and the thread count
(``--threads``, default 1 on this shared 2-core machine).
"""

from __future__ import annotations

import json
import statistics
import time

import numpy as np
import torch

from peel_model.config import ARCHS, load_model_config
from peel_model.predictor import ForcePredictor, fit_normalization
from peel_msgs_py.cliargs import ArgumentParser, positive_int

from .config import load_train_config
from .devices import device_arg, resolve_device
from .losses import total_loss
from .replay import ReplayPool
from .synthetic import synthetic_split


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def bench_arch(arch: str, *, train_steps: int, repeats: int, device: torch.device) -> dict:
    """Measure one architecture; returns the JSON fields."""
    mcfg = load_model_config().with_arch(arch)
    tcfg = load_train_config()
    trajs = synthetic_split(0, 32)
    torch.manual_seed(0)
    pred = ForcePredictor(mcfg, fit_normalization(trajs, mcfg.h)).to(device)
    pool = ReplayPool(trajs, pad_front=mcfg.h - 1)
    rng = np.random.default_rng(0)
    opt = torch.optim.Adam(pred.parameters(), lr=tcfg.lr)
    slice_len = max(tcfg.slice_len, mcfg.h + 1)

    def step() -> int:
        win = pool.sample_slices(tcfg.batch_size, slice_len, rng).windows(mcfg.h).to_torch(device)
        loss, _ = total_loss(pred, win.hist, win.v_next, win.f_next, kappa=tcfg.kappa,
                             psi_lim=tcfg.psi_lim_mm)
        opt.zero_grad()
        loss.backward()
        opt.step()
        return len(win)

    step()  # warm-up
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    n = sum(step() for _ in range(train_steps))
    if device.type == "cuda":
        torch.cuda.synchronize()
    train_sps = n / (time.perf_counter() - t0)

    pred.eval()
    out = {"train_samples_per_s": round(train_sps, 1)}
    for b in (1, 1000):
        hist = torch.randn(b, mcfg.h, 4, device=device)
        v = torch.randn(b, device=device)

        def infer(hist=hist, v=v) -> None:
            with torch.no_grad():
                pred.predict(hist, v)
            if device.type == "cuda":
                torch.cuda.synchronize()

        infer()
        out[f"infer_ms_b{b}"] = round(_median_ms(infer, repeats), 4)
    out["n_params"] = sum(p.numel() for p in pred.parameters())
    out["threads"] = torch.get_num_threads()
    out["device"] = device.type
    return out


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="peel bench model", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print JSON only (the default output)")
    p.add_argument("--arch", nargs="+", choices=ARCHS, default=list(ARCHS))
    p.add_argument("--train-steps", type=positive_int, default=20,
                   help="timed training batches per arch")
    p.add_argument("--repeats", type=positive_int, default=30,
                   help="timed inference calls per batch size")
    p.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--device", type=device_arg, default="cpu", help="cpu (default), cuda[:N], or auto")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    dev = resolve_device(args.device)
    result = {a: bench_arch(a, train_steps=args.train_steps, repeats=args.repeats, device=dev)
              for a in args.arch}
    print(json.dumps(result, indent=2))
    return 0
