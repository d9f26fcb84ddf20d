"""Cyclone DDS domain configuration: ``ROS_DOMAIN_ID`` and the loopback-only default.

By default every participant of the embedded runtime keeps DDS traffic on this machine: it uses
the loopback interface (127.0.0.1) only, multicast is off, and discovery is unicast to the local
peer 127.0.0.1 with automatic participant indices (up to :data:`MAX_PARTICIPANT_INDEX` + 1
processes per domain on one machine). The XML is handed to Cyclone DDS when the domain is
created, so nothing depends on the environment of the shell.

Opening the network (deployment next to ROS 2 machines):

* ``CYCLONEDDS_URI`` set by the user: it is used as-is (Cyclone's own variable; an XML string or
  ``file://...``), exactly as ``rmw_cyclonedds_cpp`` would use it;
* ``PEEL_DDS_NETWORK=1``: Cyclone DDS defaults (all interfaces, SPDP multicast discovery), which
  is what a stock ROS 2 Jazzy install with ``rmw_cyclonedds_cpp`` uses.
"""

from __future__ import annotations

import os

from ...errors import PeelError

#: Highest automatic participant index; each process of the graph holds one participant.
MAX_PARTICIPANT_INDEX = 31

#: Highest domain id ROS 2 allows with the default port mapping (ROS 2 docs, "domain ID").
MAX_DOMAIN_ID = 232

LOOPBACK_XML = (
    "<CycloneDDS><Domain Id=\"any\">"
    "<General><Interfaces><NetworkInterface address=\"127.0.0.1\"/></Interfaces>"
    "<AllowMulticast>false</AllowMulticast></General>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
    f"<MaxAutoParticipantIndex>{MAX_PARTICIPANT_INDEX}</MaxAutoParticipantIndex>"
    "<Peers><Peer address=\"127.0.0.1\"/></Peers></Discovery>"
    "</Domain></CycloneDDS>"
)


def domain_id(environ: dict[str, str] | None = None) -> int:
    """``ROS_DOMAIN_ID`` (default 0), checked to lie in 0..232."""
    env = os.environ if environ is None else environ
    raw = env.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return 0
    try:
        value = int(raw)
    except ValueError:
        raise PeelError(f"ROS_DOMAIN_ID must be an integer, got {raw!r}") from None
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise PeelError(f"ROS_DOMAIN_ID must lie in 0..{MAX_DOMAIN_ID}, got {value}")
    return value


def network_mode(environ: dict[str, str] | None = None) -> str:
    """``"user"`` (CYCLONEDDS_URI set), ``"network"`` (PEEL_DDS_NETWORK=1) or ``"loopback"``."""
    env = os.environ if environ is None else environ
    if env.get("CYCLONEDDS_URI", "").strip():
        return "user"
    flag = env.get("PEEL_DDS_NETWORK", "").strip().lower()
    if flag in ("1", "true", "yes", "on"):
        return "network"
    if flag not in ("", "0", "false", "no", "off"):
        raise PeelError(f"PEEL_DDS_NETWORK must be 0 or 1, got {flag!r}")
    return "loopback"


def domain_config(environ: dict[str, str] | None = None) -> str | None:
    """The XML to create the domain with, or None for Cyclone's own (env/defaults) config."""
    return LOOPBACK_XML if network_mode(environ) == "loopback" else None
