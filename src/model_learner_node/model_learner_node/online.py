"""Online learning after every task, without ROS: the learner node's work (docs/graph.md).

:class:`OnlineLearner` keeps the :class:`~model_learner_node.replay.ReplayPool` (3.3.1), runs
Algorithm 1 (:class:`~model_learner_node.maml.MetaLearner`, Eq. 26-27) or baseline 2
(:class:`~model_learner_node.baselines2.HistoryRetrainer`) on each finished task and writes the
updated weights atomically as ``out_dir/model_vNNNN.safetensors`` (+ JSON;
:func:`~peel_model.checkpoint.save_checkpoint`: temporary file + ``os.replace``,
safetensors only, never a pickle). ``NNNN`` only numbers the learner's files; the version the
planner plans it under is the planner's to give (:mod:`peel_model.versions`), and each
file's meta names it instead: ``producer`` (the learner node) and ``task`` (1-based)
(:func:`~peel_model.versions.update_meta`).

An update of Algorithm 1 is offered only when it earns its swap (:class:`~model_learner_node.gate.HeldOutGate`:
fitted without the newest peel's end, no worse than the model in use on it; else ``skipped``
with both errors named, the learner back on the weights in use; baseline 2 is the paper's), and
any update only when it predicts finite forces on the probe batch
(:func:`~peel_model.validation.check_finite_outputs`, the planner's own swap check): the
starting model is refused at construction (:class:`~peel_msgs_py.errors.CheckpointError`, so
the node exits 2), and an update that raises or fails the probe is reported ``failed`` with the
learner back on its last good weights (and meta-optimiser state).
"""

from __future__ import annotations

import json
import math
import re
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from peel_model.checkpoint import load_checkpoint, read_checkpoint_config, save_checkpoint, shipped_checkpoint
from peel_model.validation import check_finite_outputs
from peel_model.versions import update_meta
from peel_msgs_py.errors import PeelError
from peel_msgs_py.modelinfo import FAILED, OFFERED, SKIPPED, UpdateReport
from peel_msgs_py.trajectory import Trajectory

from .gate import GateConfig, HeldOutGate
from .replay import ReplayPool
from .resume import (
    LEARNED_KEPT,
    STATE_FILE,
    LearnerState,
    load_state,
    save_state,
    trajectory_digest,
)

_NUMBER_RE = re.compile(r"model_v(\d+)")


def json_safe(obj: Any) -> Any:
    """``obj`` with non-finite floats as None and unknown objects as strings (checkpoint meta)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if hasattr(obj, "item"):
        return json_safe(obj.item())
    return json.loads(json.dumps(obj, default=str))


def model_file(out_dir: Path, number: int) -> Path:
    """``out_dir/model_vNNNN.safetensors``."""
    return out_dir / f"model_v{number:04d}.safetensors"


def last_number(out_dir: Path) -> int:
    """The highest NNNN of the ``model_vNNNN.safetensors`` in ``out_dir`` (0: none)."""
    found = [_NUMBER_RE.fullmatch(p.stem) for p in out_dir.glob("model_v*.safetensors")]
    return max((int(m.group(1)) for m in found if m), default=0)


def task_number(traj: Trajectory, fallback: int) -> int:
    """1-based number of the task ``traj`` finished: ``meta.task_index + 1`` as the simulator
    set it (the number it waits for), else ``fallback`` (the count of trajectories seen)."""
    idx = traj.meta.get("task_index")
    return idx + 1 if isinstance(idx, int) and not isinstance(idx, bool) and idx >= 0 else fallback


def probe_rows(traj: Trajectory) -> np.ndarray:
    """The measured rows (q_mm, v_mmps, fx_N, fz_N) of ``traj`` for the probe batch."""
    return np.stack([traj.q, traj.v, traj.fx, traj.fz], axis=1).astype(np.float64)


class OnlineLearner:
    """Replay pool + Algorithm 1 (or baseline 2) + checked, named checkpoints (module doc)."""

    def __init__(self, values: dict[str, Any], producer: str = "model_learner_node") -> None:
        self.out_dir = Path(values["node.out_dir"])
        self.resumed = load_state(self.out_dir) if values["node.resume"] else None
        init = values["node.init_model"]
        if self.resumed is not None and self.resumed.checkpoint:
            self.init_path = self.out_dir / self.resumed.checkpoint
        else:
            self.init_path = shipped_checkpoint() if not init else Path(init)
        self.predictor = load_checkpoint(self.init_path)
        check_finite_outputs(self.predictor, what=f"the starting model {self.init_path.name}")
        self.producer = producer
        m = _NUMBER_RE.search(self.init_path.name)
        # of the last file written; never one already in out_dir (none is overwritten)
        self.number = max(int(m.group(1)) if m else 0, last_number(self.out_dir))
        self.method = values["node.method"]
        if self.method == "maml":
            from .maml import MamlConfig, MetaLearner

            self.learner: Any = HeldOutGate(MetaLearner(self.predictor, MamlConfig.from_params(values)),
                                            self.predictor, GateConfig.from_params(values))
        else:
            from .baselines2 import Baseline2Config, HistoryRetrainer

            self.learner = HistoryRetrainer(self.predictor, Baseline2Config.from_params(values))
        self.pool = ReplayPool(capacity=values["node.pool_capacity"] or None)
        self.n_tasks = 0
        self.checkpoint = ("", "")  # (file name, SHA-256) of the last update written
        self.learned: deque[str] = deque(maxlen=LEARNED_KEPT)  # digests of the tasks learned
        if self.resumed is not None:
            self.go_on(self.resumed)
        self.out_dir.mkdir(parents=True, exist_ok=True)

    def go_on(self, state: LearnerState) -> None:
        """Continue from a stopped learner's ``state`` (:mod:`~model_learner_node.resume`)."""
        self.pool.extend(state.pool)
        self.n_tasks, self.number = state.n_tasks, max(self.number, state.number)
        self.checkpoint = (state.checkpoint, state.sha256)
        self.learned.extend(state.learned)
        full = self.learner.state()
        full.update(state.learner)
        self.learner.restore(full)

    def describe(self) -> str:
        if self.resumed is not None:
            return (f"{self.method} resumed from {STATE_FILE} ({self.n_tasks} tasks seen, "
                    f"{len(self.pool)} in the replay pool, weights {self.init_path.name}), "
                    f"writing to {self.out_dir}")
        return f"{self.method} from {self.init_path.name}, writing to {self.out_dir}"

    def save(self) -> None:
        """Write the state a restarted learner goes on from (:mod:`~model_learner_node.resume`)."""
        learner = {k: v for k, v in self.learner.state().items() if k != "model"}
        save_state(self.out_dir, LearnerState(*self.checkpoint, self.number, self.n_tasks,
                                              self.pool.trajectories, learner, list(self.learned)))

    def has_learned(self, traj: Trajectory) -> bool:
        """Whether this very task was learned already (a restarted learner receives the
        bridge's recent tasks again: ``/peel/trajectory`` is transient local)."""
        return trajectory_digest(traj) in self.learned

    def learn(self, traj: Trajectory, log: Any) -> UpdateReport:
        """One update on a finished task: ``offered`` with the checkpoint written, ``failed``
        (weights restored) or ``skipped`` (nothing to learn from); then the state a restarted
        learner goes on from (:meth:`save`, after the checkpoint)."""
        report = self._learn(traj, log)
        self.save()
        return report

    def _learn(self, traj: Trajectory, log: Any) -> UpdateReport:
        self.n_tasks += 1
        self.learned.append(trajectory_digest(traj))
        task = task_number(traj, self.n_tasks)
        saved = self.learner.state()
        try:
            report = self.learner.update(traj, self.pool)
            if report.get("updated", True):
                what = f"the update after task {task}"
                check_finite_outputs(self.predictor, what=what)
                check_finite_outputs(self.predictor, probe_rows(traj), what=what)
        except Exception as exc:  # Algorithm 1 raised, or its model is unusable
            self.learner.restore(saved)
            reason = str(exc) if isinstance(exc, PeelError) else f"{type(exc).__name__}: {exc}"
            log.error(f"update after task {task} failed: {reason}; back on the last good weights")
            return UpdateReport(self.producer, task, FAILED, reason)
        finally:
            self.keep(traj, log)
        if not report.get("updated", True):
            reason = str(report.get("reason", ""))
            log.warn(f"task {task}: no update ({reason})")
            return UpdateReport(self.producer, task, SKIPPED, reason)
        self.number += 1
        meta = json_safe({**update_meta(self.producer, task), "file_number": self.number,
                          "task_meta": traj.meta, "update": report})
        path = save_checkpoint(model_file(self.out_dir, self.number), self.predictor, meta)
        log.info(f"task {task}: Algorithm 1 done in {report.get('update_s', 0):.2f} s, "
                 f"wrote {path.name}")
        self.checkpoint = (path.name, str(read_checkpoint_config(path)["safetensors_sha256"]))
        return UpdateReport(self.producer, task, OFFERED, sha256=self.checkpoint[1],
                            path=str(path.resolve()))

    def keep(self, traj: Trajectory, log: Any) -> None:
        """Add ``traj`` to the replay pool unless a measured value in it is not finite."""
        cols = (traj.t, traj.q, traj.v, traj.u, traj.fx, traj.fz)
        if all(bool(np.isfinite(np.asarray(c, dtype=np.float64)).all()) for c in cols):
            self.pool.add(traj)
        else:
            log.warn(f"task {self.n_tasks}: non-finite samples; not kept in the replay pool")
