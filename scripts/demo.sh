#!/usr/bin/env bash
# The demo command: sets up the environment, then starts a local job (controller + pods),
# runs a pipelined rollout on it, prints a summary and writes a plot and videos to out/demo.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$("$here/scripts/setup.sh" | tail -n 1)"
cd "$here"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
# Subprocesses (pods, controllers, benchmarks) import this checkout, whatever the venv points at.
export PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}"
exec "$venv/bin/vecsim" demo "$@"
