"""Faults the controller emulator can be told to commit, for tests (docs/nachi.md).

A fault is written ``KIND[:key=value,...]`` (``peel nachi-emulator --fault ...``, repeatable):

=============  ==============================================================================
kind           what the emulator does
=============  ==============================================================================
``drop``       closes the connection at task time ``t`` (the robot stops, nothing is sent)
``garbage``    sends ``n`` lines of junk (``#~!`` text and a non-ASCII line) before the sample at ``t``
``oversize``   sends ``n`` lines of 300 bytes before the sample at ``t``
``nan``        writes ``nan`` for F_RX in the ``n`` samples from ``t``
``inf``        writes ``inf`` for F_RX in the ``n`` samples from ``t``
``stall``      sends no sample for ``s`` s of controller time from ``t`` (the robot keeps moving,
               commands are still answered)
``spike``      reports F_RX = ``f`` N in the sample at ``t`` (a sensor spike; physics untouched)
``no-hello``   accepts connection ``conn`` (every one if not given) and never says ``HELLO``
``bad-hello``  greets connection ``conn`` with ``HELLO NACHI-PEEL <version>``
=============  ==============================================================================

Keys: ``t`` task time in s (default 0), ``task`` the emulator's task index (0 = first ``START``;
default: the first task that reaches ``t``), ``n`` lines (default 1), ``s`` stall length in s of
controller time (default 1.0), ``f`` spike force in N (default 22, between the bridge's 20 N
prewarning and the emulator's 25 N force alarm), ``conn`` connection index (0 = first accept),
``version`` for ``bad-hello`` (default 2). Each task fault fires once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from peel_msgs_py.errors import PeelError

KINDS = ("drop", "garbage", "oversize", "nan", "inf", "stall", "spike", "no-hello", "bad-hello")
#: Faults that act on the greeting of a connection rather than on a task.
CONNECTION_KINDS = ("no-hello", "bad-hello")


@dataclass(frozen=True)
class Fault:
    kind: str
    t: float = 0.0
    task: int | None = None
    n: int = 1
    s: float = 1.0
    f: float = 22.0
    conn: int | None = None
    version: int = 2

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise PeelError(f"fault kind {self.kind!r} is not one of {', '.join(KINDS)}")
        for name in ("t", "s", "f"):
            value = getattr(self, name)
            if not math.isfinite(value) or (name != "f" and value < 0):
                raise PeelError(f"fault {self.kind}: {name} = {value!r} must be finite and >= 0")
        for name in ("task", "conn"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise PeelError(f"fault {self.kind}: {name} = {value!r} must be >= 0")
        if self.n < 1:
            raise PeelError(f"fault {self.kind}: n = {self.n!r} must be >= 1")

    def matches_task(self, task: int) -> bool:
        return self.task is None or self.task == task

    def matches_conn(self, conn: int) -> bool:
        return self.conn is None or self.conn == conn


_INT_KEYS = ("task", "n", "conn", "version")
_FLOAT_KEYS = ("t", "s", "f")


def parse_fault(spec: str) -> Fault:
    """``KIND[:key=value,...]`` -> :class:`Fault`; :class:`PeelError` naming what is wrong."""
    kind, _, rest = spec.strip().partition(":")
    values: dict[str, object] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, raw = item.partition("=")
        if not eq or key not in _INT_KEYS + _FLOAT_KEYS:
            raise PeelError(f"fault {spec!r}: {item!r} is not key=value with a key of "
                            f"{', '.join(_INT_KEYS + _FLOAT_KEYS)}")
        try:
            values[key] = int(raw) if key in _INT_KEYS else float(raw)
        except ValueError:
            raise PeelError(f"fault {spec!r}: {key} = {raw!r} is not a number") from None
    return Fault(kind, **values)  # type: ignore[arg-type]
