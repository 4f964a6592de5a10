#!/usr/bin/env bash
# The test command: sets up the environment, then runs the whole suite.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$("$here/scripts/setup.sh" | tail -n 1)"
cd "$here"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
# Subprocesses (pods, controllers, benchmarks) import this checkout, whatever the venv points at.
export PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}"
exec "$venv/bin/python" -m pytest "$@"
