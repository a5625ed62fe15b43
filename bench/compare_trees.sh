#!/usr/bin/env bash
# Before/after of a structural change in one run: each bench runs in each tree in turn
# (same avatar, same settings, the trees interleaved per bench), so all see the same machine.
#   ROUNDS=2 bash bench/compare_trees.sh TREE [TREE ...]
#   RUN="rooms.py --only orbit" ROUNDS=3 bash bench/compare_trees.sh TREE [TREE ...]
# A TREE is a checkout of a commit (e.g. `git worktree add ../before <commit>`); all use
# this tree's .venv (PY overrides it). RUN: one bench instead of the default three (copy a
# new bench file into the older trees first). Each run's Markdown table goes to stdout,
# labelled with its tree and the load average when it started.
set -euo pipefail
py="${PY:-$(cd "$(dirname "$0")/.." && pwd)/.venv/bin/python}"
rounds="${ROUNDS:-1}"
unset PYTHONPATH  # each tree imports its own code
runs=(
  "stream.py --sessions 1,4 --seconds 6 --avatar synthetic"
  "rooms.py --viewers 1,16 --seats 2 --seconds 5 --avatar synthetic"
  "webrtc.py --sizes 512 --transports ws-jpeg,webrtc-vp8 --seconds 6 --cap-seconds 0 --samples 5 --avatar synthetic"
)
if [ -n "${RUN:-}" ]; then runs=("$RUN"); fi
for run in "${runs[@]}"; do
  for round in $(seq "$rounds"); do
    for tree in "$@"; do
      echo "### $(cd "$tree" && git log -1 --format='%h %s' | cut -c1-60) (round $round, load $(cut -d' ' -f1 /proc/loadavg)): bench/$run"
      (cd "$tree" && $py bench/$run) 2>&1 | grep -E '^\||^#|fps|p95' || true
      echo
    done
  done
done
