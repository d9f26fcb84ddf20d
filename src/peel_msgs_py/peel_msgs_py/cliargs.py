"""Command-line plumbing shared by every ``peel`` command: one-line errors and checked arguments.

Bad input gets one line naming what is wrong and exit status 2, before any work starts
(docs/CONTRACT.md, "Shared helpers"). Three pieces make that hold for every command:

* :class:`ArgumentParser`: argparse's parser, except that a usage error (unknown option, missing
  argument, a value its ``type`` refuses) raises :class:`UsageError` instead of printing the usage
  block and exiting, so it reaches the same one-line handler as every other bad input;
* argument types that refuse what the command cannot use while the arguments are parsed:
  :func:`int_arg` / :data:`positive_int` / :data:`nonnegative_int`, :func:`float_arg` /
  :data:`finite_float` / :data:`positive_float`, and comma-separated lists :func:`int_list`,
  :func:`float_list` (``nan``, ``inf`` and out-of-range values never pass a float type);
* :func:`run_main`: the one top-level handler, used by ``peel`` and by the ``python -m`` entry
  points: :class:`~peel_msgs_py.errors.PeelError` -> ``<prog>: error: <message>``, exit 2
  (or the error's own ``exit_status``, e.g. 5 for a ROS domain another graph holds);
  an :class:`OSError` that escapes a command (disk full, a file removed under it) -> one line
  naming the file, exit 1; Ctrl-C -> exit 130. No traceback for any of them.

Output locations are checked by :mod:`peel_msgs_py.outputs`.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from .errors import PeelError


class UsageError(PeelError):
    """A command-line usage error (what argparse would print with the usage block)."""

    def __init__(self, message: str, prog: str | None = None) -> None:
        super().__init__(message)
        self.prog = prog


class ArgumentParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose usage errors raise :class:`UsageError` (one line)."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(message, self.prog)


def _named(fn: Callable[[str], Any], name: str) -> Callable[[str], Any]:
    fn.__name__ = name  # argparse names the type in its own messages
    return fn


def _range_text(lo: float | None, hi: float | None, lo_open: bool) -> str:
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"<= {hi:g}")
    return " and ".join(parts)


def int_arg(min: int | None = None, max: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in ``[min, max]``."""
    rng = _range_text(min, max, False)

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if (min is not None and value < min) or (max is not None and value > max):
            raise argparse.ArgumentTypeError(f"expected an integer {rng}, got {text!r}")
        return value

    return _named(parse, f"integer {rng}".strip())


def float_arg(min: float | None = None, max: float | None = None, *,
              min_open: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number in ``[min, max]`` (``(min, max]`` with ``min_open``)."""
    rng = _range_text(min, max, min_open)

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if min is not None and (value <= min if min_open else value < min):
            raise argparse.ArgumentTypeError(f"expected a number {rng}, got {text!r}")
        if max is not None and value > max:
            raise argparse.ArgumentTypeError(f"expected a number {rng}, got {text!r}")
        return value

    return _named(parse, f"finite number {rng}".strip())


def _list_of(item: Callable[[str], Any], what: str) -> Callable[[str], tuple[Any, ...]]:
    def parse(text: str) -> tuple[Any, ...]:
        parts = [x.strip() for x in text.split(",") if x.strip()]
        if not parts:
            raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text!r}")
        try:
            return tuple(item(x) for x in parts)
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"in {text!r}: {exc}") from None

    return _named(parse, f"comma-separated {what}")


def int_list(min: int | None = None, max: int | None = None) -> Callable[[str], tuple[int, ...]]:
    """An argparse type: ``1,2,3``, each an integer in ``[min, max]``."""
    return _list_of(int_arg(min, max), "integers")


def float_list(min: float | None = None, max: float | None = None, *,
               min_open: bool = False) -> Callable[[str], tuple[float, ...]]:
    """An argparse type: ``0.1,0.5``, each a finite number in range (as :func:`float_arg`)."""
    return _list_of(float_arg(min, max, min_open=min_open), "numbers")


#: Common argument types.
positive_int = int_arg(1)
nonnegative_int = int_arg(0)
finite_float = float_arg()
positive_float = float_arg(0.0, min_open=True)


def run_main(prog: str, main: Callable[[list[str]], int | None],
             argv: Sequence[str] | None = None) -> int:
    """Run ``main(argv)`` with the one-line error handling of the module docstring."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        return int(main(args) or 0)
    except UsageError as exc:
        print(f"{exc.prog or prog}: error: {exc}", file=sys.stderr)
        return 2
    except PeelError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return int(getattr(exc, "exit_status", 2))
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        where = f" {exc.filename}" if exc.filename else ""
        print(f"{prog}: error: cannot complete{where}: {exc.strerror or exc}", file=sys.stderr)
        return 1
