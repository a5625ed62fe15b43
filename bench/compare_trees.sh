#!/usr/bin/env bash
# Before/after of a structural change in one run: each bench runs in each tree in turn
# (same avatar, same settings, the trees interleaved per bench), so all see the same machine.
#   ROUNDS=2 bash bench/compare_trees.sh TREE [TREE ...]
# A TREE is a checkout of a commit (e.g. `git worktree add ../before <commit>`); all use
# this tree's .venv. Each run's Markdown table goes to stdout, labelled with its tree.
set -euo pipefail
py="$(cd "$(dirname "$0")/.." && pwd)/.venv/bin/python"
rounds="${ROUNDS:-1}"
runs=(
  "stream.py --sessions 1,4 --seconds 6 --avatar synthetic"
  "rooms.py --viewers 1,16 --seats 2 --seconds 5 --avatar synthetic"
  "webrtc.py --sizes 512 --transports ws-jpeg,webrtc-vp8 --seconds 6 --cap-seconds 0 --samples 5 --avatar synthetic"
)
for run in "${runs[@]}"; do
  for round in $(seq "$rounds"); do
    for tree in "$@"; do
      echo "### $(cd "$tree" && git log -1 --format='%h %s' | cut -c1-60) (round $round): bench/$run"
      (cd "$tree" && $py bench/$run) 2>&1 | grep -E '^\||^#|fps|p95' || true
      echo
    done
  done
done
