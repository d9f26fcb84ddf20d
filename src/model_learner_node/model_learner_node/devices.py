"""Torch device names, checked against what this torch build and machine have.

``--device`` of ``peel train``, ``peel figures`` and ``peel bench model`` takes ``cpu``, ``cuda``,
``cuda:N`` or ``auto`` (CUDA when present, else CPU). :func:`device_arg` is the argparse type, so
``--device tpu`` or ``--device cuda`` on a machine without CUDA is a one-line usage error before
anything is loaded; :func:`resolve_device` turns a checked name into a ``torch.device``.
"""

from __future__ import annotations

import argparse

import torch

from peel_msgs_py.errors import PeelError

#: Device names peel accepts (``cuda:N`` too).
DEVICES = ("cpu", "cuda", "auto")


def check_device(name: str | None) -> torch.device:
    """``torch.device`` for ``name`` (module docstring), or PeelError saying why not."""
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise PeelError(f"unknown device {name!r} (choose cpu, cuda, cuda:N or auto)") from None
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise PeelError(f"device {name!r} is not supported (choose cpu, cuda, cuda:N or auto)")
    if not torch.cuda.is_available():
        raise PeelError(f"device {name!r} requested but CUDA is not available "
                        f"(torch {torch.__version__})")
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise PeelError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA "
                        "device(s)")
    return dev


def resolve_device(name: str | None = "cpu") -> torch.device:
    """``cpu`` (default), ``cuda[:N]``, or ``auto`` = CUDA when present."""
    return check_device(name)


def device_arg(text: str) -> str:
    """argparse type for ``--device``: the name, checked by :func:`check_device`."""
    try:
        check_device(text)
    except PeelError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


device_arg.__name__ = "device"
