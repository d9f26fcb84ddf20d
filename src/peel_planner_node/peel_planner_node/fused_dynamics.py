"""The fused dynamics: the forward model rolled out by :class:`~.fused.FusedRollout`, in sample
chunks on worker threads.

**Chunks are cut by N and ``chunk_samples`` only** (``dynamics.fused.chunk_samples``): samples
[0, c), [c, 2c), ... with the remainder last. Worker i rolls out chunks i, i + W, i + 2W, ...
with its own workspace, its ops on as many intra-op threads as the calling thread (OpenMP's
and MKL's thread counts are thread-local: a fresh thread would use every core, and a matmul
split over two threads rounds differently from one on one). Every chunk is then the same
computation on the same shapes whichever thread runs it, so the result is bit-identical for
any number of workers (``test_planner_dynamics``). It does depend on the chunk size at float
rounding: a matmul over 256 rows may be blocked differently from one over 1000.

The samples are independent, and torch releases the GIL inside every op, so the chunks run in
parallel; each runs its ops single-threaded, which at N = 1000
was faster than torch's intra-op threads over the whole batch (docs/planner.md). Run the
process with ``torch.set_num_threads(1)`` when workers > 1 (the node and the bench do), or the
two pools oversubscribe the cores.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import FusedConfig
from .fused import FusedRollout
from .fused_weights import FusedWeights, fused_support
from .history import history_window

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def chunk_spans(n: int, chunk_samples: int) -> list[tuple[int, int]]:
    """Sample ranges [a, b) of the chunks of a batch of ``n``: fixed by n and the chunk size."""
    if chunk_samples < 1:
        raise PeelError(f"dynamics.fused.chunk_samples = {chunk_samples} must be >= 1")
    return [(a, min(a + chunk_samples, n)) for a in range(0, n, chunk_samples)]


class FusedDynamics:
    """:class:`~.dynamics.Dynamics` of a ``ForcePredictor`` the fused rollout supports
    (:func:`~.fused_weights.fused_support`), with the settings of ``dynamics.fused``."""

    def __init__(self, predictor: Any, *, dt_s: float = 0.1,
                 config: FusedConfig | None = None) -> None:
        reason = fused_support(predictor)
        if reason is not None:
            raise PeelError(f"fused dynamics cannot roll out this model: {reason}")
        self.config = config if config is not None else FusedConfig()
        if self.config.workers < 1:
            raise PeelError(f"dynamics.fused.workers = {self.config.workers} must be >= 1")
        chunk_spans(1, self.config.chunk_samples)  # validates the chunk size
        predictor.eval()
        self.predictor, self.h, self.dt_s = predictor, int(predictor.h), float(dt_s)
        self.weights = FusedWeights(predictor, _DTYPES[self.config.dtype])
        self.engines = [FusedRollout(self.weights, native=self.config.native_loop)
                        for _ in range(self.config.workers)]
        self._pool: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()  # one rollout at a time (the engines hold workspaces)

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        """Predicted (q_mm, fx_N, fz_N) [N, S, 3] for ``v`` [N, S] from the end of ``history``."""
        window = history_window(history, self.h)
        spans = chunk_spans(int(v.shape[0]), self.config.chunk_samples)
        with self._lock, torch.inference_mode():
            w = self.weights.current()
            if len(spans) == 1:
                return self.engines[0].rollout(w, window, v, self.dt_s)
            used = min(len(self.engines), len(spans))
            out = torch.empty((*v.shape, 3), dtype=w.in_mean.dtype, device=w.in_mean.device)
            threads = torch.get_num_threads()

            def run(i: int) -> None:
                if i > 0:  # OpenMP's and MKL's thread counts are per thread: the caller's
                    torch.set_num_threads(threads)
                with torch.inference_mode():  # thread-local too: entered in the worker
                    for a, b in spans[i::used]:
                        out[a:b] = self.engines[i].rollout(w, window, v[a:b], self.dt_s)

            if used == 1:
                run(0)
                return out
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=len(self.engines) - 1,
                                                thread_name_prefix="peel-rollout")
            futures = [self._pool.submit(run, i) for i in range(1, used)]
            run(0)
            for f in futures:
                f.result()
            return out

    def describe(self) -> str:
        """Which implementation runs, for logs and status."""
        from .native_loop import load, status

        c = self.config
        loop = "C++ loop" if c.native_loop and load() is not None else (
            "Python loop (" + ("dynamics.fused.native_loop false" if not c.native_loop
                               else status()["reason"]) + ")")
        return (f"fused dynamics, {loop}, {c.workers} worker(s), chunks of {c.chunk_samples} "
                f"samples, {c.dtype}")

    def close(self) -> None:
        """Stop the worker threads (also done at interpreter exit)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
