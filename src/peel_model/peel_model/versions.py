"""Model versions: unique and monotonic whoever swaps a model in, and updates known by identity.

A version number taken from a file name (``model_v0003``) collides as soon as two parties swap
models: an outside file with no number becomes "the next" version, and the learner's own
numbering later produces the same number again; a wait for "version >= k" is then satisfied by
the wrong model. Here the planner is the only allocator:

* :class:`ModelLedger` gives the starting model version 0 and every *accepted* swap the next
  integer, whatever the file is called; refused swaps take no number. So versions are unique
  and strictly increasing for the planner's lifetime.
* Each :class:`~peel_msgs_py.modelinfo.ModelRecord` (shared with the simulator, which may not
  import this package) carries the model's identity: the SHA-256 of its safetensors file
  (recorded in its checkpoint JSON by :func:`~peel_model.checkpoint.save_checkpoint`)
  and, for an update of Algorithm 1, the ``producer`` and ``task`` written into the checkpoint
  meta by :func:`update_meta`; for a fast step inside a peel the ``producer`` and the
  ``fast_step`` it names (:func:`fast_meta`; no ``task``, so no wait for an update between
  peels ends on it). An outside model has no producer.
* :meth:`ModelLedger.update_for` answers "has the learner's update after task k been swapped
  in, and under which version?" by that identity, never by comparing numbers.

How the nodes use it (ROS-free here; the nodes are thin adapters): the planner keeps a ledger,
``accept``\\ s a model after :func:`~peel_model.validation.check_finite_outputs` passed,
publishes ``record.version`` on ``/peel/model_version`` and ``record.to_json()`` on the
transient-local ``/peel/model_info``; the learner writes ``update_meta(node, task)`` into each checkpoint's meta;
the simulator and ``peel graph`` wait for a record with ``is_update(producer, task)``
(:class:`peel_msgs_py.modelinfo.UpdateWait`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from peel_msgs_py.modelinfo import ModelRecord

from .checkpoint import read_checkpoint_config

__all__ = ["FAST_KEY", "PRODUCER_KEY", "TASK_KEY", "ModelLedger", "ModelRecord", "fast_meta",
           "identify", "update_meta"]

#: Meta keys of a checkpoint written by Algorithm 1's node.
PRODUCER_KEY = "producer"
TASK_KEY = "task"
FAST_KEY = "fast_step"

#: (SHA-256, producer, task, fast step) of a checkpoint: what :func:`identify` reads.
Identity = tuple[str, str | None, int | None, dict[str, Any] | None]


def update_meta(producer: str, task: int, **extra: Any) -> dict[str, Any]:
    """Checkpoint meta that names an update: who produced it, after which task (1-based)."""
    return {PRODUCER_KEY: producer, TASK_KEY: int(task), **extra}


def fast_meta(producer: str, fast: dict[str, Any], **extra: Any) -> dict[str, Any]:
    """Checkpoint meta that names a fast step inside a peel: who produced it, and the step
    (``FastResult.identity()`` of model_learner_node.fast_step)."""
    return {PRODUCER_KEY: producer, FAST_KEY: dict(fast), **extra}


def identify(path: str | Path) -> Identity:
    """(SHA-256, producer, task, fast step) of a checkpoint, from its JSON (the file was
    verified against that hash by :func:`~peel_model.checkpoint.load_checkpoint`)."""
    cfg = read_checkpoint_config(path)
    meta = cfg.get("meta") or {}
    producer = meta.get(PRODUCER_KEY)
    task = meta.get(TASK_KEY)
    fast = meta.get(FAST_KEY)
    return (str(cfg["safetensors_sha256"]),
            producer if isinstance(producer, str) else None,
            task if isinstance(task, int) and not isinstance(task, bool) else None,
            fast if isinstance(fast, dict) else None)


@dataclass
class ModelLedger:
    """The planner's record of the models it accepted, in order (module docstring)."""

    records: list[ModelRecord] = field(default_factory=list)

    @classmethod
    def start(cls, path: str | Path) -> ModelLedger:
        """A ledger whose version 0 is the starting model at ``path``."""
        ledger = cls()
        ledger.accept(path)
        return ledger

    @property
    def latest(self) -> ModelRecord:
        return self.records[-1]

    def accept(self, path: str | Path, identity: Identity | None = None) -> ModelRecord:
        """Record an accepted model; returns it with the next version. ``identity``: what
        :func:`identify` returned for ``path`` when the caller read it already."""
        sha, producer, task, *fast = identity if identity is not None else identify(path)
        version = self.records[-1].version + 1 if self.records else 0
        rec = ModelRecord(version, sha, str(path), producer, task, fast[0] if fast else None)
        self.records.append(rec)
        return rec

    def update_for(self, producer: str, task: int) -> ModelRecord | None:
        """The record of ``producer``'s update after ``task``, if it was accepted."""
        return next((r for r in self.records if r.is_update(producer, task)), None)
