"""``peel record``: record the /peel topics and /clock to an MCAP bag in the rosbag2 layout.

    peel record --out BAG [--duration S] [--topics T ...] [--chunk-size BYTES]
                [--flush-interval S] [--compression lz4|none]
    peel record --repair BAG

Records until ``--duration`` seconds (wall clock) have passed, or until SIGINT / SIGTERM; then
closes the bag properly and prints a JSON summary on stdout. A recorder killed with SIGKILL (or
a power cut) leaves a bag without its summary, a bad disk block a chunk whose CRC fails:
``--repair`` turns either into a complete bag holding every chunk whose CRC holds, reports the
dropped ones and counts the messages kept (:mod:`peel_bag.bagrepair`). A write that fails
while recording (a full disk) ends the recording with one line naming the bag, the error and
the repair command, and exit status :data:`RECORDING_FAILED` (4).
"""

from __future__ import annotations

import contextlib
import json
import signal
import sys
import time

from peel_msgs_py import held_signals
from peel_msgs_py.cliargs import ArgumentParser, positive_float, positive_int, run_main
from peel_msgs_py.errors import PeelError
from peel_msgs_py.topics import RECORDED_TOPICS, topic

from . import bag as bagmod
from .bagrepair import repair_bag

#: Exit status of a recording that could not be written (the bag is cut short).
RECORDING_FAILED = 4


def _parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="peel record",
        description="Record the /peel topics and /clock to an MCAP bag (rosbag2 layout).",
    )
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--out", metavar="BAG", help="bag directory to create (must not exist)")
    mode.add_argument("--repair", metavar="BAG",
                      help="make a bag cut short readable again, keeping its complete chunks")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="stop after S seconds of wall-clock time (default: until SIGINT/SIGTERM)")
    p.add_argument("--topics", nargs="+", default=None, metavar="TOPIC",
                   help=f"topics to record (default: all of {', '.join(RECORDED_TOPICS)})")
    p.add_argument("--cell", default="", metavar="NAMESPACE",
                   help="record the topics of the cell under NAMESPACE (e.g. /cell_0), stored "
                        "under their one-cell names /peel/... (docs/fleet.md)")
    p.add_argument("--chunk-size", type=positive_int, default=bagmod.DEFAULT_CHUNK_SIZE, metavar="BYTES",
                   help="flush a chunk when it holds this many bytes (default %(default)s)")
    p.add_argument("--flush-interval", type=positive_float, default=bagmod.DEFAULT_FLUSH_INTERVAL_S,
                   metavar="S", help="flush a chunk when it is this old (default %(default)s s)")
    p.add_argument("--compression", choices=sorted(bagmod.COMPRESSIONS), default="lz4",
                   help="chunk compression (default %(default)s)")
    return p


class _Stop:
    """SIGINT / SIGTERM set a flag; the spin loop ends and the bag is closed properly."""

    def __init__(self) -> None:
        self.requested = False
        self._old: dict[int, object] = {}

    def __enter__(self) -> _Stop:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handle)
        held_signals.release()  # a signal held since the launcher started us arrives now
        return self

    def _handle(self, signum: int, frame: object) -> None:
        self.requested = True

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)  # type: ignore[arg-type]


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``peel record``; returns the exit status."""
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    if args.repair:
        result = repair_bag(args.repair)
        for d in result.chunks_dropped:
            lost = "unknown" if d.messages is None else d.messages
            print(f"peel record: warning: dropped the chunk at byte {d.offset} ({d.reason}); "
                  f"messages lost: {lost}", file=sys.stderr)
        print(json.dumps(result.as_dict(), sort_keys=True))
        return 0
    names = list(dict.fromkeys(args.topics or RECORDED_TOPICS))
    for name in names:
        topic(name)  # unknown topic -> PeelError naming it
    if args.cell and not args.cell.startswith("/"):
        raise PeelError(f"--cell: {args.cell!r} is not an absolute namespace such as /cell_0")
    writer = bagmod.BagWriter(
        args.out, chunk_size=args.chunk_size, flush_interval_s=args.flush_interval,
        compression=args.compression,
    )
    writer.open()  # a bag path that cannot be written fails here, before any ROS set-up

    from .recorder_node import record

    t0 = time.monotonic()
    try:
        with _Stop() as stop:
            record(writer, names, args.duration, stop, cell=args.cell.rstrip("/"))
    except bagmod.BagWriteError:
        pass  # in writer.failure
    finally:
        with contextlib.suppress(bagmod.BagWriteError):
            writer.close()
    if writer.failure is not None:
        print(f"peel record: error: {writer.failure}", file=sys.stderr, flush=True)
        return RECORDING_FAILED
    summary = {
        "bag": str(args.out),
        "messages": writer.message_count,
        "chunks": writer.chunks_written,
        "topics": names,
        "duration_s": round(time.monotonic() - t0, 3),
    }
    print(json.dumps(summary, sort_keys=True), flush=True)
    return 0


def run(argv: list[str] | None = None) -> int:
    """``main`` with bad input reported as one line and exit status 2 (``python -m`` use)."""
    return run_main("peel record", main, argv)


def node_main(argv: list[str] | None = None) -> int:
    """Console script ``peel_recorder`` for ``ros2 run``: same options as ``peel record``
    (``--ros-args`` ignored)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--ros-args" in args:
        args = args[: args.index("--ros-args")]
    return run(args)


if __name__ == "__main__":
    sys.exit(run())
