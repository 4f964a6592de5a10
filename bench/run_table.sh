#!/usr/bin/env bash
# Re-run the dev machine's benchmarks of docs/benchmarks.md's table, one after another, from the
# repository root, in the project's venv (set up by scripts/setup.sh). Each writes its record to
# out/bench/<name>.json; this prints each one's RESULT line, exit status and the load it met.
set -u
cd "$(dirname "$0")/.."
venv="$(scripts/setup.sh | tail -n 1)"
source "$venv/bin/activate"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
commands=(
  "bench/bench_codec.py --rounds 30"
  "bench/bench_transport.py --rounds 10 --profile"
  "bench/bench_serving.py --wait-quiet-s 60"
  "bench/bench_pipeline.py --wait-quiet-s 60"
  "bench/bench_scaling.py --rounds 5 --wait-quiet-s 60"
  "bench/bench_control_plane.py --rounds 3"
  "bench/bench_cheap_scenes.py --rounds 3 --wait-quiet-s 60"
)
for cmd in "${commands[@]}"; do
  echo "=== $(date -u +%H:%M:%S) python $cmd (load $(cut -d' ' -f1 /proc/loadavg))"
  # shellcheck disable=SC2086  # the command's words are meant to split
  timeout 1500 python $cmd 2>&1 | grep -E "^RESULT|Error|Traceback" | cut -c1-600
  echo "rc=${PIPESTATUS[0]}"
done
echo "=== done $(date -u +%H:%M:%S)"
