#!/usr/bin/env bash
# Before/after of a structural change in one run: each bench runs in the BEFORE tree and in
# this tree, alternately (A B A B), same avatar and settings, so both see the same machine.
#   bash bench/compare_trees.sh BEFORE_TREE [ROUNDS]
# BEFORE_TREE is a checkout of the older commit (e.g. `git worktree add ../before <commit>`);
# both use this tree's .venv. Each run's Markdown table goes to stdout, labelled.
set -euo pipefail
before="$(cd "$1" && pwd)"
after="$(cd "$(dirname "$0")/.." && pwd)"
rounds="${2:-2}"
py="$after/.venv/bin/python"
runs=(
  "stream.py --sessions 1,4 --seconds 8 --avatar synthetic"
  "rooms.py --viewers 1,16 --seats 2 --seconds 6 --avatar synthetic"
  "webrtc.py --sizes 512 --transports ws-jpeg,webrtc-vp8 --seconds 8 --cap-seconds 0 --avatar synthetic"
)
for run in "${runs[@]}"; do
  for round in $(seq "$rounds"); do
    for tree in "$before" "$after"; do
      label=$([ "$tree" = "$before" ] && echo before || echo after)
      echo "### $label, round $round: bench/$run"
      (cd "$tree" && OMP_WAIT_POLICY=PASSIVE $py bench/$run) 2>&1 | grep -E '^\||^#|fps|p95' || true
      echo
    done
  done
done
