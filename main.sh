#!/usr/bin/env bash
# Command 1 of 2: set everything up (idempotent) and run the main job.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bash "$root/scripts/setup.sh"
exec "$root/.venv/bin/peel" demo "$@"
