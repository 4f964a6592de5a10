#!/usr/bin/env bash
# The test command: sets up the environment, then runs the whole suite (CI: scripts/test.sh -q).
# scripts/test.sh --fast runs the fast tier, for every change: no test marked libero (real LIBERO
# scenes) or slow. Both run in VECSIM_TEST_WORKERS worker processes (pytest-xdist; default 2, 0
# for one process), a test file's tests all in one worker, so its module's pods start once.
# Every other argument goes to pytest as it is.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$("$here/scripts/setup.sh" | tail -n 1)"
cd "$here"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
# Subprocesses (pods, controllers, benchmarks) import this checkout, whatever the venv points at.
export PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}"
args=()
for arg in "$@"; do
  if [ "$arg" = --fast ]; then args+=(-m "not libero and not slow"); else args+=("$arg"); fi
done
workers="${VECSIM_TEST_WORKERS:-2}"
if [ "$workers" != 0 ]; then args+=(-n "$workers" --dist loadfile); fi
exec "$venv/bin/python" -m pytest ${args[@]+"${args[@]}"}
