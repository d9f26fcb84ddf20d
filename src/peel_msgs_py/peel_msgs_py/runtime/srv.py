"""ROS 2 service types for node code: ``SetParameters.Request`` / ``.Response`` and friends.

Under rclpy these are the generated Jazzy classes; under the embedded runtime the IDL structs of
:mod:`peel_msgs_py.runtime.embedded.messages`. :func:`get_service_class` looks one up by name.
"""

from __future__ import annotations

from typing import Any

from ..errors import PeelError
from ._select import BACKEND, RCLPY

if BACKEND == RCLPY:  # pragma: no cover
    from rcl_interfaces.srv import (
        DescribeParameters,
        GetParameters,
        ListParameters,
        SetParameters,
    )
    from std_srvs.srv import Trigger
else:
    from .embedded.messages import (
        DescribeParameters,
        GetParameters,
        ListParameters,
        SetParameters,
        Trigger,
    )

__all__ = [
    "DescribeParameters",
    "GetParameters",
    "ListParameters",
    "SetParameters",
    "Trigger",
    "get_service_class",
]


def get_service_class(name: str) -> type[Any]:
    """The service class for ``pkg/srv/Type``; :class:`PeelError` when unknown."""
    parts = name.strip().split("/")
    if len(parts) == 2:
        parts = [parts[0], "srv", parts[1]]
    full = "/".join(parts)
    if len(parts) != 3 or parts[1] != "srv" or not all(parts):
        raise PeelError(f"unknown service type {name!r} (expected 'pkg/srv/Type')")
    if BACKEND == RCLPY:  # pragma: no cover
        try:
            from rosidl_runtime_py.utilities import get_service

            return get_service(full)
        except (AttributeError, ModuleNotFoundError, ValueError):
            raise PeelError(f"unknown service type {name!r}") from None
    from .embedded.messages import SERVICE_REGISTRY

    try:
        return SERVICE_REGISTRY[full]
    except KeyError:
        raise PeelError(f"unknown service type {name!r}") from None
