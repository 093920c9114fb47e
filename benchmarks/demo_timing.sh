#!/usr/bin/env bash
# make demo's wall time, N runs each way, interleaved (after, before, after, ...), on idle cores:
# "after" is this checkout, "before" the commit given, run from a worktree with the same venv.
#
#   bash benchmarks/demo_timing.sh 143a4e2 /tmp/timing 3
#
# Each run leaves OUT/{after,before}N/ (the demo's folder), .log and .time (bash's time). The
# table of benchmarks/results/demo_5min_cpu.md was read from those logs.
set -euo pipefail
BEFORE=${1:?a commit to compare with}; OUT=${2:?an output folder}; N=${3:-3}
REPO=$(cd "$(dirname "$0")/.." && pwd); PY=$REPO/.venv/bin/python
WT=$OUT/before_tree
mkdir -p "$OUT"
if [ ! -d "$WT" ]; then
  git -C "$REPO" worktree add --detach "$WT" "$BEFORE" >/dev/null
  # the editable install maps gsfix_online.nodes and .configs to this checkout: point them home
  ln -s ../nodes "$WT/gsfix_online/nodes"; ln -s ../configs "$WT/gsfix_online/configs"
fi
for i in $(seq 1 "$N"); do
  for arm in after before; do
    run=$OUT/$arm$i; [ -f "$run.time" ] && continue
    rm -rf "$run"; echo "$(date +%T) $arm $i: running (about 7-9 min on 2 cores)"
    if [ "$arm" = after ]; then tree=$REPO; else tree=$WT; fi
    ( cd "$OUT" && { time env PYTHONPATH="$tree" "$PY" -m gsfix_online.apps.cli demo --out "$run" \
        --no-progress > "$run.log" 2>&1; } 2> "$run.time.tmp" )
    mv "$run.time.tmp" "$run.time"; grep real "$run.time"
  done
done
