"""Online learning after every task, without ROS: the learner node's work (docs/graph.md).

:class:`OnlineLearner` keeps the :class:`~model_learner_node.replay.ReplayPool` (3.3.1), runs
Algorithm 1 (:class:`~model_learner_node.maml.MetaLearner`, Eq. 26-27) or baseline 2
(:class:`~model_learner_node.baselines2.HistoryRetrainer`) on each finished task and writes the
updated weights atomically as ``out_dir/model_vNNNN.safetensors`` (+ JSON;
:func:`~model_learner_node.checkpoint.save_checkpoint`: temporary file + ``os.replace``,
safetensors only, never a pickle).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

from peel_msgs_py.trajectory import Trajectory

from .checkpoint import load_checkpoint, save_checkpoint, shipped_checkpoint
from .replay import ReplayPool

_VERSION_RE = re.compile(r"model_v(\d+)")


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


def model_file(out_dir: Path, version: int) -> Path:
    """``out_dir/model_vNNNN.safetensors``."""
    return out_dir / f"model_v{version:04d}.safetensors"


class OnlineLearner:
    """Replay pool + Algorithm 1 (or baseline 2) + versioned checkpoints, from node values."""

    def __init__(self, values: dict[str, Any]) -> None:
        init = values["node.init_model"]
        self.init_path = shipped_checkpoint() if not init else Path(init)
        self.predictor = load_checkpoint(self.init_path)
        m = _VERSION_RE.search(self.init_path.name)
        self.version = int(m.group(1)) if m else 0
        self.method = values["node.method"]
        if self.method == "maml":
            from .maml import MamlConfig, MetaLearner

            self.learner: Any = MetaLearner(self.predictor, MamlConfig.from_params(values))
        else:
            from .baselines2 import Baseline2Config, HistoryRetrainer

            self.learner = HistoryRetrainer(self.predictor, Baseline2Config.from_params(values))
        self.pool = ReplayPool(capacity=values["node.pool_capacity"] or None)
        self.out_dir = Path(values["node.out_dir"])
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.n_tasks = 0

    def describe(self) -> str:
        return (f"{self.method} from {self.init_path.name} (v{self.version}), "
                f"writing to {self.out_dir}")

    def learn(self, traj: Trajectory, log: Any) -> Path | None:
        """One update on a finished task; the new checkpoint, or None when nothing changed."""
        self.n_tasks += 1
        report = self.learner.update(traj, self.pool)
        self.pool.add(traj)
        if not report.get("updated", True):
            log.warn(f"task {self.n_tasks}: no update ({report.get('reason', '')})")
            return None
        self.version += 1
        meta = json_safe({"version": self.version, "task": self.n_tasks,
                          "task_meta": traj.meta, "update": report})
        path = save_checkpoint(model_file(self.out_dir, self.version), self.predictor, meta)
        log.info(f"task {self.n_tasks}: Algorithm 1 done in {report.get('update_s', 0):.2f} s, "
                 f"wrote {path.name}")
        return path
