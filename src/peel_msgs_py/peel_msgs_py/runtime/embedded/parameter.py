"""Node parameters as rclpy has them: ``Parameter``, its ``Type``, exceptions, and value checks.

``Parameter(name, type_=None, value=None)`` infers the type from the value as rclpy Jazzy does
(bool, int -> INTEGER, float -> DOUBLE, str, homogeneous lists -> the array types). A parameter
is statically typed unless its descriptor has ``dynamic_typing``: setting a value of another
type is refused (an int is *not* accepted for a DOUBLE parameter, exactly as in rclpy), and a
descriptor's ``floating_point_range`` / ``integer_range`` and ``read_only`` are enforced. Every
refusal names the parameter.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Any

from ...errors import ParameterError
from .messages import (
    Parameter as ParameterMsg,
)
from .messages import (
    ParameterDescriptor,
    ParameterType,
    ParameterValue,
    SetParametersResult,
)


class ParameterException(ParameterError):
    """Base of the parameter exceptions (all are :class:`ParameterError`, hence PeelError)."""


class ParameterNotDeclaredException(ParameterException):
    """Getting or setting a parameter that was never declared."""

    def __init__(self, name: str) -> None:
        super().__init__(f"parameter '{name}' has not been declared")


class ParameterAlreadyDeclaredException(ParameterException):
    """Declaring a parameter twice."""

    def __init__(self, name: str) -> None:
        super().__init__(f"parameter '{name}' has already been declared")


class InvalidParameterTypeException(ParameterException):
    """A value whose type is not the parameter's declared type."""


class InvalidParameterValueException(ParameterException):
    """A value refused by a range, a read-only flag or an on-set callback at declaration."""


class ParameterImmutableException(ParameterException):
    """Setting a read-only parameter."""


class NoParameterOverrideProvidedException(ParameterException):
    """A parameter declared with a type but no default, and no override was given."""

    def __init__(self, name: str) -> None:
        super().__init__(f"parameter '{name}' has no default and no override was provided")



class _ParameterTypeEnum(Enum):
    NOT_SET = ParameterType.PARAMETER_NOT_SET
    BOOL = ParameterType.PARAMETER_BOOL
    INTEGER = ParameterType.PARAMETER_INTEGER
    DOUBLE = ParameterType.PARAMETER_DOUBLE
    STRING = ParameterType.PARAMETER_STRING
    BYTE_ARRAY = ParameterType.PARAMETER_BYTE_ARRAY
    BOOL_ARRAY = ParameterType.PARAMETER_BOOL_ARRAY
    INTEGER_ARRAY = ParameterType.PARAMETER_INTEGER_ARRAY
    DOUBLE_ARRAY = ParameterType.PARAMETER_DOUBLE_ARRAY
    STRING_ARRAY = ParameterType.PARAMETER_STRING_ARRAY

    @classmethod
    def from_parameter_value(cls, value: Any) -> _ParameterTypeEnum:
        """Infer the type of a Python value (rclpy's rules)."""
        if value is None:
            return cls.NOT_SET
        if isinstance(value, bool):
            return cls.BOOL
        if isinstance(value, int):
            return cls.INTEGER
        if isinstance(value, float):
            return cls.DOUBLE
        if isinstance(value, str):
            return cls.STRING
        if isinstance(value, (list, tuple)):
            if all(isinstance(v, bytes) for v in value):
                return cls.BYTE_ARRAY
            if all(isinstance(v, bool) for v in value):
                return cls.BOOL_ARRAY
            if all(isinstance(v, int) and not isinstance(v, bool) for v in value):
                return cls.INTEGER_ARRAY
            if all(isinstance(v, float) for v in value):
                return cls.DOUBLE_ARRAY
            if all(isinstance(v, str) for v in value):
                return cls.STRING_ARRAY
        if hasattr(value, "tolist"):  # numpy arrays
            return cls.from_parameter_value(value.tolist())
        raise TypeError(f"the given value is not one of the allowed types: {value!r}")

    def check(self, value: Any) -> bool:
        """Whether ``value`` has this type."""
        if self is _ParameterTypeEnum.NOT_SET:
            return value is None
        try:
            return _ParameterTypeEnum.from_parameter_value(value) is self or (
                isinstance(value, (list, tuple)) and len(value) == 0 and self.name.endswith("ARRAY")
            )
        except TypeError:
            return False

    def __str__(self) -> str:
        return f"Type.{self.name}"


class Parameter:
    """A named, typed parameter value (``rclpy.parameter.Parameter``)."""

    Type = _ParameterTypeEnum

    def __init__(self, name: str, type_: _ParameterTypeEnum | None = None, value: Any = None):
        if type_ is None:
            type_ = _ParameterTypeEnum.from_parameter_value(value)
        if not isinstance(type_, _ParameterTypeEnum):
            raise TypeError("type_ must be an instance of Parameter.Type")
        if hasattr(value, "tolist"):
            value = value.tolist()
        if isinstance(value, tuple):
            value = list(value)
        if not type_.check(value):
            raise ValueError(f"type {type_} and value {value!r} do not agree")
        self._name = name
        self._type = type_
        self._value = value

    @property
    def name(self) -> str:
        return self._name

    @property
    def type_(self) -> _ParameterTypeEnum:
        return self._type

    @property
    def value(self) -> Any:
        return self._value

    def get_parameter_value(self) -> ParameterValue:
        """The rcl_interfaces/msg/ParameterValue of this parameter."""
        pv = ParameterValue(type=self._type.value)
        t = _ParameterTypeEnum
        v = self._value
        if self._type is t.BOOL:
            pv.bool_value = v
        elif self._type is t.INTEGER:
            pv.integer_value = v
        elif self._type is t.DOUBLE:
            pv.double_value = v
        elif self._type is t.STRING:
            pv.string_value = v
        elif self._type is t.BYTE_ARRAY:
            pv.byte_array_value = [b[0] if isinstance(b, bytes) else int(b) for b in v]
        elif self._type is t.BOOL_ARRAY:
            pv.bool_array_value = list(v)
        elif self._type is t.INTEGER_ARRAY:
            pv.integer_array_value = list(v)
        elif self._type is t.DOUBLE_ARRAY:
            pv.double_array_value = list(v)
        elif self._type is t.STRING_ARRAY:
            pv.string_array_value = list(v)
        return pv

    def to_parameter_msg(self) -> ParameterMsg:
        return ParameterMsg(name=self._name, value=self.get_parameter_value())

    @classmethod
    def from_parameter_msg(cls, msg: ParameterMsg) -> Parameter:
        return cls(msg.name, value=parameter_value_to_python(msg.value))

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, Parameter)
            and (other.name, other.type_, other.value) == (self._name, self._type, self._value)
        )

    def __repr__(self) -> str:
        return f"Parameter({self._name!r}, {self._type}, {self._value!r})"


def parameter_value_to_python(pv: ParameterValue) -> Any:
    """rcl_interfaces/msg/ParameterValue -> Python value (None for NOT_SET)."""
    t = pv.type
    table = {
        ParameterType.PARAMETER_NOT_SET: lambda: None,
        ParameterType.PARAMETER_BOOL: lambda: bool(pv.bool_value),
        ParameterType.PARAMETER_INTEGER: lambda: int(pv.integer_value),
        ParameterType.PARAMETER_DOUBLE: lambda: float(pv.double_value),
        ParameterType.PARAMETER_STRING: lambda: str(pv.string_value),
        ParameterType.PARAMETER_BYTE_ARRAY: lambda: [bytes([b]) for b in pv.byte_array_value],
        ParameterType.PARAMETER_BOOL_ARRAY: lambda: list(pv.bool_array_value),
        ParameterType.PARAMETER_INTEGER_ARRAY: lambda: list(pv.integer_array_value),
        ParameterType.PARAMETER_DOUBLE_ARRAY: lambda: list(pv.double_array_value),
        ParameterType.PARAMETER_STRING_ARRAY: lambda: list(pv.string_array_value),
    }
    if t not in table:
        raise ParameterError(f"unknown parameter type {t}")
    return table[t]()


def check_against_descriptor(param: Parameter, descriptor: ParameterDescriptor) -> str | None:
    """Why ``param`` violates ``descriptor`` (type, read-only aside), or None when it is fine."""
    name = param.name
    if not descriptor.dynamic_typing and descriptor.type != ParameterType.PARAMETER_NOT_SET:
        expected = _ParameterTypeEnum(descriptor.type)
        if param.type_ is not expected:
            return (
                f"parameter '{name}': wrong parameter type, expected '{expected.name}' "
                f"got '{param.type_.name}' ({param.value!r})"
            )
    v = param.value
    if descriptor.floating_point_range and isinstance(v, float):
        r = descriptor.floating_point_range[0]
        ok = r.from_value - 1e-12 <= v <= r.to_value + 1e-12 and math.isfinite(v)
        if ok and r.step > 0 and not math.isclose(v, r.to_value):
            k = (v - r.from_value) / r.step
            ok = math.isclose(k, round(k), abs_tol=1e-9)
        if not ok:
            return (
                f"parameter '{name}' = {v!r} is out of range [{r.from_value}, {r.to_value}]"
                + (f" step {r.step}" if r.step > 0 else "")
            )
    if descriptor.integer_range and isinstance(v, int) and not isinstance(v, bool):
        r = descriptor.integer_range[0]
        ok = r.from_value <= v <= r.to_value
        if ok and r.step > 0 and v != r.to_value:
            ok = (v - r.from_value) % r.step == 0
        if not ok:
            return (
                f"parameter '{name}' = {v!r} is out of range [{r.from_value}, {r.to_value}]"
                + (f" step {r.step}" if r.step > 0 else "")
            )
    return None


def refused(reason: str) -> SetParametersResult:
    return SetParametersResult(successful=False, reason=reason)


def accepted() -> SetParametersResult:
    return SetParametersResult(successful=True, reason="")
