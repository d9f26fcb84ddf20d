"""Summarise ``scripts/flaky.sh``'s runs: per test, the runs it failed in (JUnit XML read with
the standard library). Prints JSON; exit status 0 when no test failed in any run, else 1."""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path


def summarise(folder: Path, runs: int) -> dict[str, object]:
    """{"runs", "tests", "failed": {test id: [run numbers]}, "missing_runs"} of the folder."""
    failed: dict[str, list[int]] = {}
    tests: set[str] = set()
    missing = []
    for i in range(1, runs + 1):
        path = folder / f"run_{i}.xml"
        if not path.is_file():
            missing.append(i)  # pytest died before it wrote its report
            continue
        for case in ET.parse(path).getroot().iter("testcase"):
            tid = f"{case.get('classname')}::{case.get('name')}"
            tests.add(tid)
            if case.find("failure") is not None or case.find("error") is not None:
                failed.setdefault(tid, []).append(i)
    return {"folder": str(folder), "runs": runs, "tests": len(tests),
            "passed_every_run": len(tests) - len(failed), "failed": failed,
            "missing_runs": missing}


def main() -> int:
    rep = summarise(Path(sys.argv[1]), int(sys.argv[2]))
    print(json.dumps(rep, indent=1))
    return 0 if not rep["failed"] and not rep["missing_runs"] else 1


if __name__ == "__main__":
    sys.exit(main())
