#!/usr/bin/env bash
# Runs gymnasium's own tests/vector against vecsim's HTTPVectorEnv (docs/gymnasium.md).
# Usage: scripts/gym_vector_tests/run.sh GYMNASIUM_CHECKOUT [VECSIM_CHECKOUT] [pytest args...]
# Takes tests/ at the tag of the installed gymnasium (or GYM_REF, e.g. a commit) into a temporary folder (never into vecsim).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
gym_repo="$1"; shift
vecsim_repo="$(cd "${1:-$here/../..}" && pwd)"; [ $# -gt 0 ] && shift
py="${PYTHON:-$HOME/.cache/vecsim/venv/bin/python}"
version="$("$py" -c 'import gymnasium; print(gymnasium.__version__)')"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
git -C "$gym_repo" archive "${GYM_REF:-v$version}" tests | tar -x -C "$work"
cp "$here/conftest.py" "$here/gymtests_shim.py" "$work/"
cd "$work"
VECSIM_REPO="$vecsim_repo" PYTHONPATH="$vecsim_repo" MUJOCO_GL=egl "$py" -m pytest -q -p no:cacheprovider \
  -o addopts="" --timeout 120 "${@:-tests/vector}"
