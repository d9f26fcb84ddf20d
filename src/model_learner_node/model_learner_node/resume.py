"""The learner's state on disk, so that a learner that stops (killed, its machine restarted)
comes back where it stopped (docs/fleet.md, "The learner dies and comes back").

After every finished task :class:`~model_learner_node.online.OnlineLearner` writes
``out_dir/learner_state.safetensors`` (atomically, :func:`peel_msgs_py.atomic.atomic_write_bytes`;
safetensors, so reading it runs no code):

* ``pool.NNNN``: each trajectory of the replay pool (3.3.1, Algorithm 1 step 4) as T x 7 rows in
  :data:`~peel_msgs_py.trajectory.FIELDS` order, in the units the learner holds them (mm, mm/s,
  N, s: exactly the values it learned from, no conversion); its outcome, params and meta in the
  header's metadata under the same key;
* ``opt.<i>.<name>``: the meta-optimiser's state (Adam's moments of the Eq. 27 step), its
  ``param_groups`` as JSON;
* the counters (tasks seen, updates made, the number of the last checkpoint written), the
  name and SHA-256 of the checkpoint that holds the weights theta, and the content digests of
  the last :data:`LEARNED_KEPT` tasks learned (:func:`trajectory_digest`): ``/peel/trajectory``
  is transient local, so a restarted learner receives the bridge's recent tasks again and
  drops those it had learned.

:func:`load_state` reads it back: the checkpoint it names must exist with that SHA-256, so a
state and weights from two different moments are refused, never mixed. A learner resumed
from it makes the very update the stopped one would have made next (the same bytes).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.numpy import save

from peel_model.checkpoint import read_checkpoint_config
from peel_msgs_py.atomic import atomic_write_bytes
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import FIELDS, Trajectory

#: File name of the state, in ``node.out_dir`` beside the checkpoints.
STATE_FILE = "learner_state.safetensors"
#: How many digests of learned tasks the state keeps (the bridge's history holds 10).
LEARNED_KEPT = 1000
#: Format tag in the file's metadata.
FORMAT = "peel.learner_state/1"


class LearnerStateError(PeelError):
    """The state file in ``node.out_dir`` cannot be gone on from (the message names it)."""


@dataclass
class LearnerState:
    """What a learner needs besides theta to go on where it stopped."""

    checkpoint: str  # file name in out_dir of the weights theta ("" = none written yet)
    sha256: str  # that file's SHA-256
    number: int  # of the last model_vNNNN written
    n_tasks: int  # finished tasks seen
    pool: list[Trajectory]  # the replay pool, oldest first
    learner: dict[str, Any] = field(default_factory=dict)  # the updater's state() less "model"
    learned: list[str] = field(default_factory=list)  # digests of the tasks learned, oldest first


def _trajectory_entry(traj: Trajectory) -> tuple[np.ndarray, str]:
    rows = np.stack([np.asarray(getattr(traj, f), dtype=np.float64) for f in FIELDS], axis=1)
    header = {"outcome": traj.outcome, "params": {str(k): float(v) for k, v in traj.params.items()},
              "meta": traj.meta}
    return np.ascontiguousarray(rows.reshape(len(traj), len(FIELDS))), json.dumps(header)


def trajectory_digest(traj: Trajectory) -> str:
    """SHA-256 of a trajectory's samples, outcome, params and meta: the same finished task
    received twice has the same digest."""
    rows, _ = _trajectory_entry(traj)
    header = json.dumps({"outcome": traj.outcome, "params": traj.params, "meta": traj.meta},
                        sort_keys=True, default=str)
    return hashlib.sha256(rows.tobytes() + header.encode()).hexdigest()


def _split_optimizer(opt: dict[str, Any] | None) -> tuple[dict[str, np.ndarray], Any]:
    """Adam's ``state_dict`` as arrays (``opt.<i>.<name>``) and its JSON-able remainder."""
    if opt is None:
        return {}, None
    arrays = {f"opt.{i}.{name}": value.detach().cpu().numpy()
              for i, entry in opt["state"].items() for name, value in entry.items()}
    return arrays, opt["param_groups"]


def save_state(out_dir: Path, state: LearnerState) -> Path:
    """Write ``out_dir/learner_state.safetensors`` atomically (module docstring)."""
    tensors: dict[str, np.ndarray] = {}
    meta = {"format": FORMAT, "checkpoint": state.checkpoint, "sha256": state.sha256,
            "number": str(state.number), "n_tasks": str(state.n_tasks),
            "learned": json.dumps(state.learned[-LEARNED_KEPT:])}
    for i, traj in enumerate(state.pool):
        key = f"pool.{i:04d}"
        tensors[key], meta[key] = _trajectory_entry(traj)
    learner = dict(state.learner)
    opt_arrays, groups = _split_optimizer(learner.pop("opt", None))
    tensors.update(opt_arrays)
    meta["learner"] = json.dumps({**learner, "opt_param_groups": groups,
                                  "has_opt": groups is not None})
    return atomic_write_bytes(out_dir / STATE_FILE, save(tensors, metadata=meta))


def _optimizer(arrays: dict[str, np.ndarray], groups: Any) -> dict[str, Any]:
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in arrays.items():
        _, i, name = key.split(".", 2)
        state.setdefault(int(i), {})[name] = torch.from_numpy(value.copy())
    return {"state": dict(sorted(state.items())), "param_groups": groups}


def _read(path: Path) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    try:
        with safe_open(str(path), framework="numpy") as f:
            meta = dict(f.metadata() or {})
            arrays = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 (safe_open)
    except (OSError, SafetensorError) as exc:
        raise LearnerStateError(f"learner state {path}: not a readable safetensors file "
                                f"({exc})") from None
    if meta.get("format") != FORMAT:
        raise LearnerStateError(f"learner state {path}: format {meta.get('format')!r}, "
                                f"expected {FORMAT!r}")
    return meta, arrays


def load_state(out_dir: Path) -> LearnerState | None:
    """The state in ``out_dir`` (None without a state file); :class:`PeelError` naming the
    file when it cannot be used (unreadable, or its checkpoint missing or changed)."""
    path = out_dir / STATE_FILE
    if not path.exists():
        return None
    meta, arrays = _read(path)
    try:
        pool = []
        for key in sorted(k for k in arrays if k.startswith("pool.")):
            header, rows = json.loads(meta[key]), arrays[key]
            pool.append(Trajectory(**{f: rows[:, j].copy() for j, f in enumerate(FIELDS)},
                                   outcome=header["outcome"], params=header["params"],
                                   meta=header["meta"]))
        learner = json.loads(meta["learner"])
        groups = learner.pop("opt_param_groups")
        if learner.pop("has_opt"):
            learner["opt"] = _optimizer({k: v for k, v in arrays.items()
                                         if k.startswith("opt.")}, groups)
        learned = [str(d) for d in json.loads(meta["learned"])]
        state = LearnerState(meta["checkpoint"], meta["sha256"], int(meta["number"]),
                             int(meta["n_tasks"]), pool, learner, learned)
    except (KeyError, ValueError, TypeError, IndexError, PeelError) as exc:
        raise LearnerStateError(f"learner state {path}: malformed "
                                f"({type(exc).__name__}: {exc})") from None
    _check_checkpoint(path, out_dir, state)
    return state


def _check_checkpoint(path: Path, out_dir: Path, state: LearnerState) -> None:
    if not state.checkpoint:
        return  # no update written yet: the learner starts from its init model
    try:
        recorded = read_checkpoint_config(out_dir / state.checkpoint).get("safetensors_sha256")
    except PeelError as exc:
        raise LearnerStateError(f"learner state {path}: its weights {state.checkpoint}: "
                                f"{exc}") from None
    if recorded != state.sha256:
        raise LearnerStateError(f"learner state {path}: its weights {state.checkpoint} have "
                                f"SHA-256 {str(recorded)[:12]}..., the state was written with "
                                f"{state.sha256[:12]}...: remove the state or the folder, or "
                                f"set node.resume:=false")
