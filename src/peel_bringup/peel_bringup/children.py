"""The launcher's child processes (``peel graph``, ``peel fleet``; docs/graph.md): each node in
its own process group with the stop signals held until its handlers are in, stopped in order
(SIGINT, then SIGTERM, then SIGKILL, each only after the previous went unanswered; the recorder
last), and the environment every node gets."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from peel_msgs_py import discovery, held_signals
from peel_msgs_py.params import config_dir

RECORDER = "recorder"


def _child_setup() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Own process group (one Ctrl-C is handled in order by the launcher); SIGTERM to the child
    when the launcher dies (Linux PR_SET_PDEATHSIG); SIGINT/SIGTERM held until the child's own
    handlers are installed (:mod:`peel_msgs_py.held_signals`)."""
    os.setpgrp()
    held_signals.hold()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)
    except (OSError, AttributeError):  # not Linux: children then rely on the launcher's stop
        pass


@dataclass
class Child:
    """One started process."""

    name: str
    cmd: list[str]
    log: Path
    proc: subprocess.Popen[bytes] | None = None
    stopping: bool = False
    reported: bool = False

    def start(self, env: dict[str, str], verbose: bool) -> None:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        out = None if verbose else self.log.open("wb")
        try:
            self.proc = subprocess.Popen(self.cmd, stdout=out, stderr=subprocess.STDOUT
                                         if out is not None else None, env=env,
                                         preexec_fn=_child_setup)
        finally:
            if out is not None:
                out.close()

    @property
    def pid(self) -> int:
        return self.proc.pid if self.proc is not None else -1

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def signal(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, sig)

    def stop(self, timeout_s: float, *, signalled: bool = False) -> int | None:
        """SIGINT (unless ``signalled`` already), then SIGTERM, then SIGKILL, each only after
        the previous one went unanswered; returns the exit status."""
        if self.proc is None:
            return None
        self.stopping = True
        for sig, wait in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 5.0),
                          (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            if not (signalled and sig == signal.SIGINT):
                self.signal(sig)
            try:
                self.proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                continue
        return self.proc.poll()

    def tail(self, n: int = 8) -> str:
        try:
            lines = self.log.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join("    " + line for line in lines[-n:])


class Interrupt:
    """SIGINT / SIGTERM set a flag; the launcher then stops the graph in order."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    def install(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handle)

    def _handle(self, signum: int, frame: Any) -> None:
        self.signum = signum

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def child_env() -> dict[str, str]:
    """The nodes' environment: this one, confined to the machine unless the user opened it."""
    env = dict(os.environ)
    discovery.confine(env)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("PEEL_CONFIG_DIR", str(config_dir()))
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def tear_down(children: list[Child], timeout_s: float) -> int | None:
    """One SIGINT per node (simulator or Nachi bridge, planner, learner), each waited for (then
    SIGTERM, SIGKILL after the grace period); the recorder last, so the bag holds everything.
    Returns the recorder's exit status (None without one)."""
    nodes = [c for c in children if c.name != RECORDER]
    for child in nodes:
        child.signal(signal.SIGINT)
        child.stopping = True
    for child in nodes:
        child.stop(timeout_s, signalled=True)
    code = None
    for child in children:
        if child.name == RECORDER:
            time.sleep(0.5)  # let the last messages reach the recorder
            code = child.stop(timeout_s)
    return code
