"""``--ros-args`` command-line arguments, parsed as rcl does.

Supported inside ``--ros-args ... [--]`` (several sections allowed):
``-p|--param [node:]name:=value`` (value parsed as YAML, like rcl), ``--params-file FILE``,
``-r|--remap [node:]from:=to`` (including ``__node:=`` and ``__ns:=``),
``--log-level [name:=]LEVEL``, ``-e|--enclave X`` (accepted, unused). Anything else inside a
ROS section is refused with a :class:`PeelError`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ...errors import PeelError


@dataclass
class RosArgs:
    """What the ROS sections of an argument list say."""

    params_files: list[Path] = field(default_factory=list)
    #: (node name or None for all nodes, parameter name, value), in order of appearance
    params: list[tuple[str | None, str, Any]] = field(default_factory=list)
    #: (node name or None, from, to)
    remaps: list[tuple[str | None, str, str]] = field(default_factory=list)
    log_level: str | None = None

    def extend(self, other: RosArgs) -> None:
        self.params_files += other.params_files
        self.params += other.params
        self.remaps += other.remaps
        self.log_level = other.log_level or self.log_level


def parse_param_value(text: str) -> Any:
    """Value of ``-p name:=value``: YAML scalar or flow sequence, as rcl parses it."""
    try:
        value = yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError:
        return text
    if value is None:
        return text
    return value


def _split_assignment(text: str, flag: str) -> tuple[str | None, str, str]:
    if ":=" not in text:
        raise PeelError(f"{flag} expects 'name:=value', got {text!r}")
    left, right = text.split(":=", 1)
    node = None
    if ":" in left:
        node, left = left.split(":", 1)
    if not left:
        raise PeelError(f"{flag} expects 'name:=value', got {text!r}")
    return node, left, right


def parse(argv: Sequence[str] | None) -> tuple[RosArgs, list[str]]:
    """Split ``argv`` into the ROS arguments and the remaining (user) arguments."""
    ros = RosArgs()
    rest: list[str] = []
    args = list(argv or [])
    i = 0
    in_ros = False
    while i < len(args):
        a = args[i]
        if a == "--ros-args":
            in_ros = True
        elif in_ros and a == "--":
            in_ros = False
        elif not in_ros:
            rest.append(a)
        else:
            def value(i: int = i, a: str = a) -> str:
                if i + 1 >= len(args):
                    raise PeelError(f"--ros-args: {a} needs a value")
                return args[i + 1]

            if a in ("-p", "--param"):
                node, name, text = _split_assignment(value(), a)
                ros.params.append((node, name, parse_param_value(text)))
                i += 1
            elif a == "--params-file":
                path = Path(os.path.expanduser(value()))
                if not path.is_file():
                    raise PeelError(f"--params-file: no such file {path}")
                ros.params_files.append(path)
                i += 1
            elif a in ("-r", "--remap"):
                node, src, dst = _split_assignment(value(), a)
                ros.remaps.append((node, src, dst))
                i += 1
            elif a == "--log-level":
                text = value()
                ros.log_level = text.split(":=", 1)[1] if ":=" in text else text
                i += 1
            elif a in ("-e", "--enclave"):
                i += 1
            elif a in ("--disable-stdout-logs", "--disable-rosout-logs", "--enable-rosout-logs",
                       "--disable-external-lib-logs", "--enable-stdout-logs"):
                pass
            else:
                raise PeelError(f"unknown ROS argument {a!r}")
        i += 1
    return ros, rest


def remove_ros_args(args: Sequence[str] | None = None) -> list[str]:
    """``rclpy.utilities.remove_ros_args``: the arguments outside ``--ros-args`` sections."""
    import sys

    return parse(list(sys.argv if args is None else args))[1]
