#!/usr/bin/env bash
# Idempotent environment setup: creates .venv (Python 3.11 or 3.12), installs the pinned
# dependencies, ROS 2 Jazzy's rclpy and message packages (pip wheels, requirements-ros.txt) and
# the eleven peel packages in editable mode (in dependency order). Re-running is a no-op when nothing changed (a stamp
# file holds the hash of every file that affects the install).
#
# On a machine with a sourced ROS 2 Jazzy install (ROS_DISTRO=jazzy) the venv sees the system
# site-packages and uses that rclpy: the ros-* wheels are not installed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
PY="${PEEL_PYTHON:-}"
if [ -z "$PY" ]; then
  for cand in python3.12 python3.11 python3; do
    if command -v "$cand" >/dev/null 2>&1; then
      ver="$("$cand" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)" || continue
      case "$ver" in 3.11|3.12) PY="$cand"; break ;; esac
    fi
  done
fi
if [ -z "$PY" ]; then
  echo "setup: error: need Python 3.11 or 3.12 (set PEEL_PYTHON to its path)" >&2
  exit 2
fi
if [ "${ROS_DISTRO:-}" = "jazzy" ]; then
  ros_mode="system"  # rclpy and the message packages come from the sourced Jazzy install
  ros_reqs=()
  venv_opts=(--system-site-packages)
else
  ros_mode="wheels"
  ros_reqs=(-r requirements-ros.txt)
  venv_opts=()
fi
# The peel packages, each after the ones it depends on (test/test_workspace.py holds the order).
PACKAGES=(peel_msgs_py peel_model peel_bag peel_bridge peel_sim_node peel_nachi_bridge peel_nachi_emulator
          model_learner_node peel_planner_node peel_residual peel_experiments peel_bringup)
# pip install -q, without the known noise: setuptools' "Editable installation" notice (one
# 10-line block per package, a UserWarning of the build backend, ignored by message) and pip's
# "Location ... is ignored" line for each find-links / index directory of the machine's pip
# configuration that lacks a package. Anything else on stderr (every error) is shown.
pip_quiet() {  # pip's stdout as is; its stderr through the filter (pipefail: pip's status)
  { PYTHONWARNINGS="ignore:Editable installation" \
      .venv/bin/python -m pip install -q --disable-pip-version-check "$@" 2>&1 1>&3 3>&- \
      | { grep -v -E "^WARNING: Location '[^']*' is ignored: it is neither a file nor a directory\.$" || true; } >&2
  } 3>&1
}
stamp=".venv/.peel-setup-stamp"
hash="$ros_mode-$(cat requirements.txt requirements-ros.txt requirements-dev.txt src/*/setup.py src/*/package.xml | sha256sum | cut -c1-16)"
if ! { [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$hash" ] && [ -x .venv/bin/peel ]; }; then
  echo "setup: creating .venv with $PY and installing pinned dependencies, rclpy from $ros_mode" \
       "(first run takes a minute)" >&2
  if [ -f "$stamp" ] && [ "${hash%%-*}" != "$(cut -d- -f1 "$stamp")" ]; then
    rm -rf .venv  # switched between the rclpy wheels and a sourced Jazzy: start afresh
  fi
  [ -x .venv/bin/python ] || "$PY" -m venv "${venv_opts[@]}" .venv
  pip_quiet --upgrade pip setuptools wheel
  pip_quiet -r requirements.txt -r requirements-dev.txt "${ros_reqs[@]}"
  if ! .venv/bin/python -c "import rclpy, geometry_msgs.msg, rosgraph_msgs.msg" 2>/dev/null; then
    echo "setup: error: rclpy is not importable from .venv (ROS_DISTRO=${ROS_DISTRO:-unset});" \
         "source /opt/ros/jazzy/setup.bash or unset ROS_DISTRO to use the pip wheels" >&2
    exit 2
  fi
  editable=()
  for pkg in "${PACKAGES[@]}"; do editable+=(-e "src/$pkg"); done
  pip_quiet --no-deps --no-build-isolation "${editable[@]}"
  echo "$hash" > "$stamp"
  echo "setup: done" >&2
fi
# the planner's C++ model-step loop: compiled once into this venv (.venv/peel_native/, keyed by
# the source hash; ~25-110 s), never while planning; optional (without a compiler the Python
# loop runs, same results), so a failure here does not stop setup
.venv/bin/python -m peel_planner_node.native_loop || true
