"""Which model the planner plans with, and what became of each update of the learner: the JSON
carried by ``/peel/model_info`` and ``/peel/model_update`` (std_msgs/msg/String; the topic table
in :mod:`peel_msgs_py.topics`, docs/interfaces.md), and the wait for the learner's update after
task k, by identity (docs/graph.md, "The model swap"). No ROS here.

* :class:`ModelRecord` (``/peel/model_info``, transient local, published by the planner on every
  accepted model): the version the planner allocated (0 = starting model, +1 per accepted swap,
  never taken from a file name; :class:`peel_model.versions.ModelLedger`) and the
  model's identity: SHA-256 of its safetensors file, path, and for an update of Algorithm 1 the
  ``producer`` (the learner node's name) and ``task`` (1-based) from the checkpoint's meta;
  for a fast step inside a peel (``model_learner_node.fast_step``) ``task`` is null and
  ``fast`` names it: ``{"task": k, "step": i, "fit_samples": [0, c], "check_samples": [c, n]}``
  (the running task k, the i-th fast step in it, the samples it was fitted on and checked on).
* :class:`UpdateReport` (``/peel/model_update``, published by the learner once per finished
  task): ``swapped`` (the planner accepted it), ``refused`` (the planner's reason), ``failed``
  (Algorithm 1 raised, or its model predicts non-finite forces: never offered), ``skipped``
  (nothing to learn from, e.g. a trajectory shorter than one slice). A learner that serves
  several cells (docs/fleet.md) publishes one report per update and cell on that cell's topic,
  the cell's namespace in ``cell``.
* :class:`UpdateWait`: the simulator waits between tasks, and ``peel graph`` after the last
  one, for the outcome of the learner's update after task k: the planner's record of exactly
  that update (producer and task), or the learner's report that it failed, was refused or
  skipped. A model swapped in by anyone else never ends the wait, whatever its version.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace

from .errors import PeelError

#: Status of an update of the learner (:class:`UpdateReport`).
SWAPPED, REFUSED, FAILED, SKIPPED = "swapped", "refused", "failed", "skipped"
#: Status the learner's own core gives an update before the planner answered.
OFFERED = "offered"
STATUSES = (SWAPPED, REFUSED, FAILED, SKIPPED, OFFERED)


def _loads(text: str, what: str) -> dict:
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PeelError(f"{what}: not JSON ({exc.msg})") from None
    if not isinstance(obj, dict):
        raise PeelError(f"{what}: expected a JSON object")
    return obj


def _check_int(what: str, name: str, value: object, minimum: int, optional: bool) -> None:
    """``value`` an integer >= ``minimum`` (None allowed when ``optional``), else PeelError."""
    if value is None and optional:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise PeelError(f"{what}: '{name}' must be an integer >= {minimum}"
                        f"{' or null' if optional else ''}, got {value!r}")


def _check_str(what: str, name: str, value: object, optional: bool) -> None:
    if not (isinstance(value, str) or (optional and value is None)):
        raise PeelError(f"{what}: '{name}' must be a string, got {value!r}")


@dataclass(frozen=True)
class ModelRecord:
    """One model the planner planned with: its version and identity."""

    version: int
    sha256: str
    path: str
    producer: str | None = None
    task: int | None = None
    fast: dict | None = None  # the fast step that made it (module docstring), else None

    def __post_init__(self) -> None:
        _check_int("model info", "version", self.version, 0, False)
        _check_int("model info", "task", self.task, 1, True)
        for name in ("sha256", "path", "producer"):
            _check_str("model info", name, getattr(self, name), name == "producer")
        if self.fast is not None:
            if not isinstance(self.fast, dict):
                raise PeelError(f"model info: 'fast' must be an object or null, got {self.fast!r}")
            _check_int("model info", "fast.task", self.fast.get("task"), 1, False)
            _check_int("model info", "fast.step", self.fast.get("step"), 1, False)

    def is_update(self, producer: str, task: int) -> bool:
        """Whether this is ``producer``'s update after ``task``."""
        return self.producer == producer and self.task == task

    def to_json(self) -> str:
        """The JSON of ``/peel/model_info`` (``fast`` only when a fast step made the model)."""
        obj = asdict(self)
        if obj["fast"] is None:
            del obj["fast"]
        return json.dumps(obj, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ModelRecord:
        obj = _loads(text, "model info")
        try:
            return cls(**obj)
        except TypeError as exc:
            raise PeelError(f"model info: {exc}") from None


@dataclass(frozen=True)
class UpdateReport:
    """What became of ``producer``'s update after ``task`` (module docstring)."""

    producer: str
    task: int
    status: str
    reason: str = ""
    sha256: str | None = None
    path: str | None = None
    version: int | None = None  # the planner's version, once it is known to have swapped
    cell: str | None = None  # the namespace of the cell whose planner this reports on (fleet)

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise PeelError(f"model update: status {self.status!r} is not one of {STATUSES}")
        _check_int("model update", "task", self.task, 0, False)
        _check_int("model update", "version", self.version, 0, True)
        for name in ("producer", "reason", "sha256", "path", "cell"):
            _check_str("model update", name, getattr(self, name),
                       name in ("sha256", "path", "cell"))

    @property
    def failed(self) -> bool:
        """The update did not reach the planner although there was one to make."""
        return self.status in (FAILED, REFUSED)

    def describe(self) -> str:
        """Short text for logs and task lines."""
        if self.status == SWAPPED:
            return f"swapped in as model v{self.version}" if self.version is not None else SWAPPED
        return f"{self.status}: {self.reason}" if self.reason else self.status

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> UpdateReport:
        obj = _loads(text, "model update")
        try:
            return cls(**obj)
        except TypeError as exc:
            raise PeelError(f"model update: {exc}") from None


@dataclass
class UpdateWait:
    """The planner's records and the learner's reports as they arrive; :meth:`outcome` answers
    whether ``producer``'s update after task k has come (module docstring)."""

    producer: str
    records: list[ModelRecord] = field(default_factory=list)
    reports: dict[int, UpdateReport] = field(default_factory=dict)

    @property
    def latest(self) -> ModelRecord | None:
        """The model the planner announced last."""
        return self.records[-1] if self.records else None

    def add_record(self, rec: ModelRecord) -> None:
        if rec not in self.records:  # a latched record may be delivered twice
            self.records.append(rec)

    def add_report(self, rep: UpdateReport) -> None:
        if rep.producer == self.producer:
            self.reports[rep.task] = rep

    def reported(self, task: int) -> UpdateReport | None:
        """The learner's own report on its update after ``task`` (any final status), else None:
        what a run waits for before it stops, so that the report is delivered and recorded."""
        rep = self.reports.get(task)
        return rep if rep is not None and rep.status != OFFERED else None

    def outcome(self, task: int) -> UpdateReport | None:
        """``swapped`` with the planner's version once its record of the update is in; the
        learner's report when the update failed, was refused or skipped; else None (wait)."""
        rec = next((r for r in self.records if r.is_update(self.producer, task)), None)
        if rec is not None:
            return UpdateReport(self.producer, task, SWAPPED, sha256=rec.sha256, path=rec.path,
                                version=rec.version)
        rep = self.reports.get(task)
        if rep is not None and rep.status in (FAILED, REFUSED, SKIPPED):
            return replace(rep, version=None)
        return None
