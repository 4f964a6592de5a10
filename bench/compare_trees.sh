#!/usr/bin/env bash
# Run benchmarks of two checkouts of vecsim turn about, in the same minutes on the same machine:
# before, after, before, after ... (each benchmark interleaves its own contenders; this
# interleaves the two trees, so that load and the machine hit both alike).
#
#   bash bench/compare_trees.sh BEFORE_DIR AFTER_DIR OUT_DIR [REPEATS] [-- "bench_x.py args" ...]
#
# BEFORE_DIR / AFTER_DIR: scratch checkouts (e.g. `git worktree add --detach /tmp/before <rev>`:
# each benchmark also writes its usual records under that tree's out/bench and docs/img); each
# tree's bench/ runs with that tree first on PYTHONPATH (pods and workers it starts inherit it),
# in the project's venv (scripts/setup.sh). Without commands after `--`, the seven commands of
# bench/run_table.sh run. Each run's RESULT line goes to OUT_DIR/<bench>_<before|after>_<i>.json
# and the log to OUT_DIR/compare.log.
set -u
if [ $# -lt 3 ]; then
  sed -n '2,13p' "$0"
  exit 2
fi
before="$(cd "$1" && pwd)"
after="$(cd "$2" && pwd)"
mkdir -p "$3"
out="$(cd "$3" && pwd)"
repeats="${4:-1}"
shift $(( $# < 4 ? $# : 4 ))
[ "${1:-}" = "--" ] && shift
commands=("$@")
if [ ${#commands[@]} -eq 0 ]; then
  commands=(
    "bench_codec.py --rounds 30"
    "bench_transport.py --rounds 6"
    "bench_serving.py"
    "bench_pipeline.py"
    "bench_scaling.py --rounds 5"
    "bench_control_plane.py --rounds 3"
    "bench_cheap_scenes.py --rounds 3"
  )
fi
cd "$(dirname "$0")/.."
venv="$(scripts/setup.sh | tail -n 1)"
# shellcheck disable=SC1091
source "$venv/bin/activate"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
log="$out/compare.log"
for cmd in "${commands[@]}"; do
  name="${cmd%%.py*}"
  for i in $(seq 1 "$repeats"); do
    for side in before after; do
      tree="$before"
      [ "$side" = after ] && tree="$after"
      echo "=== $(date -u +%H:%M:%S) $side $i: python bench/$cmd (load $(cut -d' ' -f1 /proc/loadavg))" | tee -a "$log"
      # shellcheck disable=SC2086  # the command's words are meant to split
      (cd "$tree" && PYTHONPATH="$tree" timeout 1500 python bench/$cmd) > "$out/run.txt" 2>&1
      rc=$?
      grep -E "^RESULT" "$out/run.txt" | sed 's/^RESULT //' > "$out/${name}_${side}_${i}.json"
      grep -E "Error|Traceback" "$out/run.txt" | tail -n 3 | tee -a "$log"
      echo "rc=$rc" | tee -a "$log"
    done
  done
done
rm -f "$out/run.txt"
echo "=== done $(date -u +%H:%M:%S)" | tee -a "$log"
