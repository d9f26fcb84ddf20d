"""Declare a node's parameters from their :class:`~peel_msgs_py.params.ParamSpec` list, with
descriptors, so that rclpy itself enforces them and ``ros2 param describe`` shows them:

* ``description`` (the spec's, with its equation or section), ``additional_constraints``
  (allowed values, where a spec lists them);
* ``FloatingPointRange`` / ``IntegerRange`` where the spec has a minimum or maximum;
* ``read_only`` unless the spec is ``dynamic`` (safe to change on a running node).

rclpy refuses a wrong-typed value (its type is the default's: an integer for a DOUBLE is
refused), an out-of-range value and a change of a read-only parameter, from a parameter file,
``-p`` or a ``set_parameters`` call, and the node keeps its old value. An on-set callback
(:class:`SpecCheck`) adds what descriptors cannot say: finite floats, allowed values. At
declaration any refusal raises :class:`~peel_msgs_py.errors.ParameterError` naming the
parameter (the node's ``main`` prints it as one line and exits 2).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import (
    InvalidParameterTypeException,
    ParameterException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..errors import ParameterError, PeelError
from ..params import ParamSpec

_INT64 = (-(2**63), 2**63 - 1)


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ``ParameterDescriptor`` of a spec (type from its default, ranges, read-only)."""
    desc = ParameterDescriptor(
        name=spec.name,
        type=getattr(Parameter.Type, spec.ros_type).value,
        description=spec.description,
        read_only=not spec.dynamic,
    )
    if spec.choices is not None:
        desc.additional_constraints = "one of: " + ", ".join(str(c) for c in spec.choices)
    if spec.min is None and spec.max is None:
        return desc
    if spec.type is float:
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(spec.min) if spec.min is not None else -math.inf,
            to_value=float(spec.max) if spec.max is not None else math.inf, step=0.0)]
    elif spec.type is int:
        desc.integer_range = [IntegerRange(
            from_value=math.ceil(spec.min) if spec.min is not None else _INT64[0],
            to_value=math.floor(spec.max) if spec.max is not None else _INT64[1], step=1)]
    return desc


class SpecCheck:
    """On-set-parameters callback: every new value must pass its spec's :meth:`ParamSpec.check`
    (finite floats, allowed values); the reason names the parameter."""

    def __init__(self, specs: Iterable[ParamSpec]) -> None:
        self.specs = {s.name: s for s in specs}

    def __call__(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            spec = self.specs.get(param.name)
            if spec is None:
                continue
            try:
                spec.check(param.value)
            except PeelError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)


def declare(node: Node, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare ``specs`` on ``node`` (overrides from ``--params-file`` / ``-p`` apply, as rclpy
    does) and return every declared value as a flat ``name -> value`` dict.

    Raises :class:`ParameterError` naming the parameter when rclpy or :class:`SpecCheck`
    refuses an override. Names rclpy declares itself (``use_sim_time``) are left to it.
    """
    specs = list(specs)
    node.add_on_set_parameters_callback(SpecCheck(specs))
    for spec in specs:
        if node.has_parameter(spec.name):
            continue
        try:
            node.declare_parameter(spec.name, spec.default, descriptor(spec))
        except InvalidParameterTypeException as exc:
            raise ParameterError(_type_message(spec, _text(exc, spec.name))) from None
        except ParameterException as exc:  # out of range, refused by SpecCheck, read-only
            raise ParameterError(_value_message(spec.name, _text(exc, spec.name))) from None
    return {name: p.value for name, p in node.get_parameters_by_prefix("").items()}


def _text(exc: Exception, name: str) -> str:
    """rclpy's message without the ``: <name>`` it appends."""
    text = str(exc.args[0]) if exc.args else str(exc)
    return text[: -len(name) - 2] if text.endswith(f": {name}") else text


_TYPE_RE = re.compile(r"to '(?P<value>.*)' of type '(?P<got>\w+)'")


def _type_message(spec: ParamSpec, text: str) -> str:
    """The message of :meth:`ParamSpec.check` for the same refusal (docs and code agree)."""
    m = _TYPE_RE.search(text)
    if m is None:
        return f"parameter '{spec.name}': {text}"
    hint = " (write a float, e.g. 1.0)" if spec.ros_type == "DOUBLE" and m["got"] == "INTEGER" \
        else ""
    return (f"parameter '{spec.name}': wrong type, expected {spec.ros_type} got {m['got']} "
            f"({m['value']}){hint}")


def _value_message(name: str, text: str) -> str:
    """rclpy: "Invalid parameter value (v) for parameter. Reason: <reason>"; the reason names
    the parameter (a descriptor's range, or :class:`SpecCheck`'s message)."""
    reason = text.split("Reason: ", 1)[-1]
    return reason if reason.startswith(f"parameter '{name}'") else f"parameter '{name}': {reason}"


def _named(result: SetParametersResult, name: str) -> SetParametersResult:
    if not result.successful and name not in result.reason:
        result.reason = f"parameter '{name}': {result.reason}"
    return result


class NamedRefusals:
    """Node mixin: a refused ``set_parameters`` names the parameter in its reason.

    rclpy's own reasons name it for a range or read-only refusal but not for a wrong type
    ("Wrong parameter type, expected 'Type.DOUBLE' got 'Type.INTEGER'"); the parameter services
    call :meth:`set_parameters_atomically` once per parameter, so the name is added there.
    """

    def set_parameters_atomically(self, parameter_list: list[Parameter]) -> SetParametersResult:
        result = super().set_parameters_atomically(parameter_list)  # type: ignore[misc]
        return _named(result, parameter_list[0].name) if len(parameter_list) == 1 else result

    def set_parameters(self, parameter_list: list[Parameter]) -> list[SetParametersResult]:
        results = super().set_parameters(parameter_list)  # type: ignore[misc]
        return [_named(r, p.name) for p, r in zip(parameter_list, results, strict=True)]
