"""The bridge's health for ``/diagnostics`` (ROS-free; :mod:`peel_msgs_py.diagnostics`).

Levels: ERROR while there is no link to the controller (or the bridge gave up on it); WARN for
:data:`~peel_msgs_py.diagnostics.HOLD_S` wall seconds after a fault counter rose (a STOP for a
stalled stream, for bad lines or at the 20 N prewarning of section 4.2, an ``ALARM``, bad lines,
a lost link); OK otherwise.
"""

from __future__ import annotations

from peel_msgs_py.diagnostics import ERROR, WARN, Check, RecentRises, Status, make_status

from .bridge import DISCONNECTED, BridgeStats

#: fault counter -> what a monitor is told while it is recent.
FAULTS = {
    "stall_stops": "controller stream stalled: STOP sent",
    "bad_line_stops": "bad lines in a row: STOP sent",
    "prewarning_stops": "force at the prewarning: STOP sent",
    "alarms": "controller ALARM",
    "bad_lines": "bad lines from the controller",
    "disconnects": "controller link lost",
}


def fault_counts(stats: BridgeStats) -> dict[str, int]:
    """The counters :data:`FAULTS` names, from the bridge's statistics."""
    stops = dict(stats.stops)  # one copy: the bridge thread adds reasons
    return {"stall_stops": stops.get("stalled", 0), "bad_line_stops": stops.get("bad_lines", 0),
            "prewarning_stops": stops.get("prewarning", 0),
            "alarms": len(stats.alarms), "bad_lines": sum(stats.bad_lines.values()),
            "disconnects": stats.disconnects}


def bridge_status(stats: BridgeStats, state: str, gave_up: str | None, endpoint: str,
                  controller: str | None, recent: RecentRises, now: float) -> Status:
    """The link's status: state, connection counts, bad lines per kind, STOPs per reason."""
    counts = fault_counts(stats)
    checks: list[Check] = [(WARN, FAULTS[name]) for name in FAULTS
                           if name in recent.update(counts, now)]
    if gave_up:
        checks.append((ERROR, f"giving up: {gave_up}"))
    elif state == DISCONNECTED:
        checks.append((ERROR, "no link to the controller" +
                       (f": {stats.last_failure}" if stats.last_failure else "")))
    values: dict[str, object] = {
        "link state": state, "controller": controller, "endpoint": endpoint,
        "connects": stats.connects, "reconnects": max(stats.connects - 1, 0),
        "connect failures": stats.connect_failures, "disconnects": stats.disconnects,
        "bad lines": counts["bad_lines"],
        **{f"bad lines ({kind})": n for kind, n in sorted(dict(stats.bad_lines).items())},
        "STOPs": sum(n for reason, n in dict(stats.stops).items() if reason != "shutdown"),
        "stall STOPs": counts["stall_stops"], "bad-line STOPs": counts["bad_line_stops"],
        "prewarning STOPs": counts["prewarning_stops"], "alarms": counts["alarms"],
        "refused V": stats.refused_v, "dropped commands": stats.dropped_commands,
        "last failure": stats.last_failure or None,
    }
    return make_status("peel_nachi_bridge: controller link", endpoint, checks, values,
                       ok_message=f"link {state}")
