"""Which ROS runtime backs ``peel_msgs_py.runtime``: real rclpy or the embedded Cyclone DDS one.

Automatic: rclpy when it is importable *and* a ROS 2 install is sourced (``ROS_DISTRO`` set),
else the embedded runtime. Jazzy's rclpy wheels in the venv (which the Nachi bridge node uses
directly) do not switch the other nodes over by themselves. ``PEEL_RUNTIME=rclpy`` forces rclpy
(a :class:`PeelError` when it is missing), ``PEEL_RUNTIME=dds`` forces the embedded runtime even
where rclpy exists. The choice is made once, at first import, and is the same for every module
of the runtime.
"""

from __future__ import annotations

import os

from ..errors import PeelError

RCLPY = "rclpy"
DDS = "dds"


def choose_backend(env: str | None = None) -> str:
    """Return ``"rclpy"`` or ``"dds"`` from ``PEEL_RUNTIME`` (or ``env``) and what is installed."""
    want = (os.environ.get("PEEL_RUNTIME", "") if env is None else env).strip().lower()
    if want not in ("", RCLPY, DDS):
        raise PeelError(f"PEEL_RUNTIME must be 'rclpy' or 'dds', got {want!r}")
    if want == DDS or (not want and not os.environ.get("ROS_DISTRO")):
        return DDS
    try:
        import rclpy  # noqa: F401
    except ImportError:
        if want == RCLPY:
            raise PeelError(
                "PEEL_RUNTIME=rclpy but rclpy is not importable (source a ROS 2 Jazzy install)"
            ) from None
        return DDS
    return RCLPY


BACKEND: str = choose_backend()
