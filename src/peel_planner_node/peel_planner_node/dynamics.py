"""What the planner rolls out: the Dynamics protocol and its implementations.

A :class:`Dynamics` maps the measured history (a :class:`~peel_msgs_py.trajectory.Trajectory`
ending at the current sample) and N velocity sequences ``v`` [N, S] -- one velocity per 100 ms
model step -- to the predicted samples [N, S, 3] with columns (q_mm, fx_N, fz_N). This is line 9
of Algorithm 2, ``x <- x + F_theta(x, v_t) dt``, batched over the N samples.

- :class:`LearnedDynamics` wraps the forward model
  (``model_learner_node.predictor.ForcePredictor``, Eq. 1-2): q advances by v dt, the forces
  come from the model fed with the last h rows [q, v, fx, fz].
- :class:`OracleDynamics` wraps any object with the simulator's
  ``rollout(v: ndarray[N, S]) -> ndarray[N, S, 3]`` (``peel_sim_node.env.PeelEnv``): the true,
  noise-free dynamics, for tests and for the oracle baseline. This package may not import the
  simulator (docs/CONTRACT.md), so the env is duck-typed.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory


@runtime_checkable
class Dynamics(Protocol):
    """Batched forward simulation used by the planner (Algorithm 2, line 9)."""

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        """Predicted (q_mm, fx_N, fz_N) [N, S, 3] for velocities ``v`` [N, S] (mm/s)."""
        ...


def history_window(history: Trajectory, h: int) -> np.ndarray:
    """The last ``h`` state rows [q, v, fx, fz] of ``history`` (Eq. 2), shape (h, 4).

    A history shorter than h (the first control periods of a task) is padded at the front with
    its first row with v = 0: the blade stood still at C before the task started.
    """
    if len(history) == 0:
        raise PeelError("history 't' is empty: the planner needs at least the sample at t=0")
    rows = history.states()[-h:]
    if not np.all(np.isfinite(rows)):
        raise PeelError("history holds non-finite q, v, fx or fz in its last samples")
    if rows.shape[0] < h:
        first = rows[:1].copy()
        first[0, 1] = 0.0
        rows = np.concatenate([np.repeat(first, h - rows.shape[0], axis=0), rows], axis=0)
    return rows


class LearnedDynamics:
    """The learned forward model F_theta (Eq. 1-2) as planner dynamics.

    Each model step s: F_{s+1} = predictor.predict(window_s, v_s), q_{s+1} = q_s + v_s dt,
    v_{s+1} = v_s (the velocity command is assumed tracked inside the rollout, Eq. 2's noise is
    what MPPI samples), then the window slides by one row. The windows are views into one
    preallocated [N, h + S, 4] buffer, so no tensor is concatenated in the loop.

    ``fast=True`` (default) runs the ``ours`` / ``cnn-lstm`` network through
    :class:`~.fused.FusedConvAttentionLSTM`, the same function with fewer ops and FLOPs (one
    matmul for the three kernels, shift-invariant window positions computed once, the LSTM on
    preallocated buffers, normalisation folded into the force update); its rearranged weights
    are cached and rebuilt whenever a parameter or buffer of the predictor changes (in place or
    not), so updates by the learner are seen. Other architectures use ``predictor.predict``.

    **Rollout workers** (``workers``, ``min_chunk``; the planner sets them from
    ``mppi.rollout_workers`` / ``mppi.min_samples_per_worker``): the N samples are independent,
    so a fused rollout of N >= 2 x min_chunk samples is split into up to ``workers`` contiguous
    chunks, each rolled out on its own thread with its own workspace (torch releases the GIL
    inside every op). The result is bit-identical to one chunk (``test_planner_dynamics``), so
    it does not depend on the number of workers. Each chunk runs its ops single-threaded, which
    at N = 1000 was faster than torch's intra-op threads over the whole batch (86 vs 95 ms per
    50-step rollout on 2 cores, docs/planner.md); run the process with
    ``torch.set_num_threads(1)`` when workers > 1, or the two pools oversubscribe the cores.

    ``native=True`` (default) runs the fused model-step loop in C++ when it can be built
    (:mod:`~.native_loop`; bit-identical, ~18 % faster at N = 50).

    **Models that roll themselves out.** The one capability check: a predictor with a
    ``rollout_from(history, v, dt_s)`` method (a model with a compensation term,
    :class:`model_learner_node.compensated.CompensatedPredictor`, whose terms need the sample
    times and whose speed response turns commands into speeds) is rolled out by that method, step
    by step; the fused path, which reproduces only the plain network, is not used for it.
    """

    def __init__(self, predictor: Any, *, dt_s: float = 0.1, fast: bool = True,
                 workers: int = 1, min_chunk: int = 256, native: bool = True) -> None:
        if not hasattr(predictor, "predict") or not hasattr(predictor, "h"):
            raise PeelError("model must be a ForcePredictor with .h and .predict(hist, v_next)")
        self.predictor = predictor
        self.h = int(predictor.h)
        self.dt_s = float(dt_s)
        try:
            p = next(predictor.parameters())
            self.dtype, self.device = p.dtype, p.device
        except (AttributeError, StopIteration):
            self.dtype, self.device = torch.float32, torch.device("cpu")
        if hasattr(predictor, "eval"):
            predictor.eval()
        own = getattr(predictor, "rollout_from", None)
        self.model_rollout = own if callable(own) else None
        self.fused = None
        if fast and self.model_rollout is None:
            from .fused import FusedConvAttentionLSTM

            if FusedConvAttentionLSTM.supports(predictor):
                self.fused = FusedConvAttentionLSTM(predictor, native=native)
        self.native = native
        self._chunks: list[Any] = []
        self._pool: ThreadPoolExecutor | None = None
        self._pool_size = 0
        self.set_workers(workers, min_chunk)

    def set_workers(self, workers: int, min_chunk: int = 256) -> None:
        """Roll out up to ``workers`` sample chunks of at least ``min_chunk`` in parallel."""
        if int(workers) < 1 or int(min_chunk) < 1:
            raise PeelError(f"rollout workers = {workers} and min_chunk = {min_chunk} must be >= 1")
        self.workers, self.min_chunk = int(workers), int(min_chunk)

    def _chunk_count(self, n: int) -> int:
        if self.fused is None:
            return 1
        return max(1, min(self.workers, n // self.min_chunk))

    def _rollout_chunks(self, window: np.ndarray, v: torch.Tensor, k: int) -> torch.Tensor:
        from .fused import FusedConvAttentionLSTM

        while len(self._chunks) < k - 1:  # chunk 0 uses self.fused; one workspace per chunk
            self._chunks.append(FusedConvAttentionLSTM(self.predictor, native=self.native))
        if self._pool is None or self._pool_size < k - 1:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
            self._pool = ThreadPoolExecutor(max_workers=k - 1, thread_name_prefix="peel-rollout")
            self._pool_size = k - 1
        parts = torch.tensor_split(v, k, dim=0)

        def run(fused: Any, part: torch.Tensor) -> torch.Tensor:
            with torch.inference_mode():  # thread-local: entered in the worker thread too
                return fused.rollout(window, part, self.dt_s)

        futures = [self._pool.submit(run, f, p)
                   for f, p in zip(self._chunks[:k - 1], parts[1:], strict=True)]
        first = run(self.fused, parts[0])
        return torch.cat([first, *(f.result() for f in futures)], dim=0)

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        """Predicted (q, fx, fz) [N, S, 3] for ``v`` [N, S] from the end of ``history``."""
        if self.model_rollout is not None:
            with torch.inference_mode():
                return self.model_rollout(history, v, self.dt_s)
        if self.fused is not None:
            window = history_window(history, self.h)
            k = self._chunk_count(int(v.shape[0]))
            if k > 1:
                return self._rollout_chunks(window, v, k)
            with torch.inference_mode():
                return self.fused.rollout(window, v, self.dt_s)
        h = self.h
        n, s = v.shape
        window = history_window(history, h)
        with torch.inference_mode():
            base = torch.as_tensor(window, dtype=self.dtype, device=self.device)
            v = v.to(dtype=self.dtype, device=self.device)
            buf = torch.empty((n, h + s, 4), dtype=self.dtype, device=self.device)
            buf[:, :h] = base
            # q_s = q_now + dt * cumsum(v): computed once for all steps
            buf[:, h:, 0] = base[-1, 0] + self.dt_s * torch.cumsum(v, dim=1)
            buf[:, h:, 1] = v
            for k in range(s):
                buf[:, h + k, 2:4] = self.predictor.predict(buf[:, k:k + h], v[:, k])
            return buf[:, h:][:, :, [0, 2, 3]]


class OracleDynamics:
    """The simulator's exact, noise-free dynamics (``env.rollout``) as planner dynamics.

    ``env`` is anything with ``rollout(v: ndarray[N, S]) -> ndarray[N, S, 3]`` that simulates
    from its own current state (``PeelEnv``); the history argument is ignored because the env
    already is at the end of it.
    """

    def __init__(self, env: Any, *, dtype: torch.dtype = torch.float32) -> None:
        if not callable(getattr(env, "rollout", None)):
            raise PeelError("env must provide rollout(v) -> ndarray[N, S, 3]")
        self.env = env
        self.dtype = dtype

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        """Predicted (q, fx, fz) [N, S, 3] by the env for ``v`` [N, S] (mm/s)."""
        out = np.asarray(self.env.rollout(v.detach().cpu().numpy().astype(np.float64)))
        if out.shape != (*v.shape, 3):
            raise PeelError(f"env.rollout returned shape {out.shape}, expected {(*v.shape, 3)}")
        return torch.as_tensor(out, dtype=self.dtype)
