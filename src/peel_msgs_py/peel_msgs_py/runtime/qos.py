"""QoS for node code: ``rclpy.qos`` under rclpy, its embedded mirror otherwise.

    from peel_msgs_py.runtime.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy
"""

from __future__ import annotations

from ._select import BACKEND, RCLPY

if BACKEND == RCLPY:  # pragma: no cover
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        LivelinessPolicy,
        QoSPresetProfiles,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_parameter_events,
        qos_profile_parameters,
        qos_profile_sensor_data,
        qos_profile_services_default,
        qos_profile_system_default,
    )
else:
    from .embedded.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        LivelinessPolicy,
        QoSPresetProfiles,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_parameter_events,
        qos_profile_parameters,
        qos_profile_sensor_data,
        qos_profile_services_default,
        qos_profile_system_default,
    )

__all__ = [
    "DurabilityPolicy",
    "HistoryPolicy",
    "LivelinessPolicy",
    "QoSPresetProfiles",
    "QoSProfile",
    "ReliabilityPolicy",
    "qos_profile_parameter_events",
    "qos_profile_parameters",
    "qos_profile_sensor_data",
    "qos_profile_services_default",
    "qos_profile_system_default",
]
