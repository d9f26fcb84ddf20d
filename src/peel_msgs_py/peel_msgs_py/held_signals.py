"""SIGINT and SIGTERM held from a child's start until its handlers are installed.

A launcher that stops its children with one SIGINT each may send it while a child is still
importing (torch alone takes seconds): Python's default handler would then raise
``KeyboardInterrupt`` at some line of an import and print a traceback. The launcher therefore
starts every child with both signals blocked (:func:`hold`, between fork and exec; the signal
mask survives ``exec``), and the child unblocks them (:func:`release`) once its own handlers are
in place: a signal that came in the meantime is delivered then, to the right handler. Started any
other way (``ros2 run``, a terminal) nothing is blocked and :func:`release` changes nothing.
"""

from __future__ import annotations

import signal

#: The signals a peel process stops on.
STOP_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM})


def hold() -> None:
    """Block the stop signals in this process (and in what it ``exec``s)."""
    signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)


def release() -> None:
    """Unblock the stop signals; one that arrived while they were held is delivered now."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
