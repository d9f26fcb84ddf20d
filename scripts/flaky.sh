#!/usr/bin/env bash
# Run the process tests (pytest mark `process`: node processes, DDS, real-time TCP) N times in a
# row, each run a fresh pytest process and so a fresh ROS domain (test/conftest.py), and print
# which tests failed and how often. Exit status 0 when every run passed, else 1.
#
#   scripts/flaky.sh N [pytest args...]      e.g. scripts/flaky.sh 10, scripts/flaky.sh 3 -k graph
#
# Each run's JUnit XML and log are kept under runs/flaky/<time>/ (run_<i>.xml, run_<i>.log).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
n="${1:-}"
case "$n" in ''|*[!0-9]*|0) echo "flaky.sh: error: N must be a positive whole number, got '${n}'" >&2; exit 2 ;; esac
shift
bash "$root/scripts/setup.sh"
cd "$root"
out="runs/flaky/$(date +%Y%m%d-%H%M%S)"
mkdir -p "$out"
for i in $(seq 1 "$n"); do
  start=$SECONDS
  set +e
  .venv/bin/python -m pytest -m process -q -p no:cacheprovider --junitxml="$out/run_$i.xml" "$@" \
    >"$out/run_$i.log" 2>&1
  rc=$?
  set -e
  echo "flaky.sh: run $i/$n: exit $rc, $((SECONDS - start)) s: $(tail -n 1 "$out/run_$i.log")" >&2
done
exec .venv/bin/python "$root/scripts/flaky_summary.py" "$out" "$n"
