"""What a benchmark's JSON says of the machine and the moment it ran on (``peel bench ...``):
benchmarks on a shared 2-core machine are read beside its load."""

from __future__ import annotations

import os
import platform
import time
from typing import Any


def run_context(load_before: tuple[float, float, float]) -> dict[str, Any]:
    """The load average (1, 5, 15 min) before and after the run, the machine and the time."""
    return {
        "load_average_1_5_15": {"before": [round(x, 2) for x in load_before],
                                "after": [round(x, 2) for x in os.getloadavg()]},
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, "
                   f"{platform.python_implementation()} {platform.python_version()}",
        "at": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
