#!/usr/bin/env bash
# Runs a command while simulated host stalls hit both CPUs (bench/c/stalls.c: a SCHED_FIFO
# 99 task per CPU that holds it for 0.5..MAX_MS ms every GAP_MIN_MS..EVERY_MS ms), to see
# which tests a stalling machine breaks before a CI machine does. The stall tasks end with
# the command, also when it fails or is interrupted, and so does whatever the command left
# running. Exits with the command's status.
#
#   bash scripts/under-stalls.sh cargo test --workspace --no-fail-fast
#   MAX_MS=20 EVERY_MS=300 bash scripts/under-stalls.sh cargo test --test standby
#   MAX_MS=2 GAP_MIN_MS=4 EVERY_MS=8 bash scripts/under-stalls.sh cargo test --workspace
#
# Needs root (SCHED_FIFO 99) and gcc. Defaults: MAX_MS 8, GAP_MIN_MS 100, EVERY_MS 400 on
# CPU 1 and twice those gaps on CPU 0 (about the stalls of docs/measurements.md, "The host's
# stalls"). Gaps of a few ms instead (the third line: 13 % of CPU 1 and 7 % of CPU 0, as
# measured, in bursts of 0.5-2 ms) stand for a contended host, on which every task runs slower.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -gt 0 ] || { echo "usage: bash scripts/under-stalls.sh COMMAND [ARG ...]" >&2; exit 2; }
max_ms=${MAX_MS:-8}
every_ms=${EVERY_MS:-400}
gap_min_ms=${GAP_MIN_MS:-100}
bin=$(mktemp -d)/stalls
gcc -O2 -o "$bin" bench/c/stalls.c
pids=()
cmd=""
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  # The command runs in a session of its own: whatever it started and left (a test
  # binary's child after the runner was stopped, say) is stopped with it, and named.
  if [ -n "$cmd" ]; then
    left=$(pgrep -s "$cmd" | tr '\n' ' ' || true)
    if [ -n "$left" ]; then
      echo "under-stalls: stopping the command's processes still running: $left" >&2
      pkill -TERM -s "$cmd" || true
      for _ in 1 2 3 4 5 6 7 8 9 10; do pgrep -s "$cmd" >/dev/null || break; sleep 0.5; done
      pkill -KILL -s "$cmd" || true
    fi
  fi
  wait "${pids[@]}" 2>/dev/null || true
  rm -rf "$(dirname "$bin")"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
"$bin" 1 "$max_ms" "$every_ms" "$gap_min_ms" & pids+=($!)
"$bin" 0 "$max_ms" $((every_ms * 2)) $((gap_min_ms * 2)) & pids+=($!)
sleep 0.2
for p in "${pids[@]}"; do
  kill -0 "$p" 2>/dev/null || { echo "under-stalls: a stall task did not start (its error is above; root?)" >&2; exit 1; }
done
echo "under-stalls: stalls of up to $max_ms ms every $gap_min_ms..$every_ms ms on CPU 1, $((gap_min_ms * 2))..$((every_ms * 2)) ms on CPU 0" >&2
# In the background and waited for, so that a signal to this script runs its traps at once
# (the command is stopped with the stall tasks). setsid does not fork here (a background
# job is not a process-group leader), so $! is the new session's id.
setsid "$@" <&0 & cmd=$!
status=0
wait "$cmd" || status=$?
exit "$status"
