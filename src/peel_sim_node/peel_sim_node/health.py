"""The simulator bridge's health for ``/diagnostics`` (ROS-free; :mod:`peel_msgs_py.diagnostics`).

Levels: WARN while the lockstep waits longer than ``node.cmd_timeout_s`` of wall time for the
``/peel/cmd_vel`` answering a sample (it is re-sending it), or when the last task was aborted
(no command within ``node.cmd_give_up_s``); OK otherwise.
"""

from __future__ import annotations

from peel_msgs_py.diagnostics import WARN, Check, Status, make_status


def sim_status(source: str, phase: str, finished: int, tasks: int, model_version: int | None,
               unanswered_s: float | None, cmd_timeout_s: float,
               last_outcome: str | None) -> Status:
    """``unanswered_s``: wall s since the waiting sample was first sent (None between tasks)."""
    checks: list[Check] = []
    if unanswered_s is not None and unanswered_s >= cmd_timeout_s:
        checks.append((WARN, f"no /peel/cmd_vel answering the sample for {unanswered_s:.1f} s "
                             "(re-sending it)"))
    if last_outcome == "aborted":
        checks.append((WARN, f"task {finished} aborted: no command within the give-up time"))
    values: dict[str, object] = {
        "source": source, "phase": phase, "tasks finished": finished,
        "tasks": tasks if tasks > 0 else "unbounded", "model version": model_version,
        "unanswered for (s)": unanswered_s, "last outcome": last_outcome,
    }
    return make_status("peel_sim_node: simulator bridge", f"peel_sim_node ({source})", checks,
                       values, ok_message=f"{phase}, {finished} tasks finished")
