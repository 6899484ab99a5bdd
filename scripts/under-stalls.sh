#!/usr/bin/env bash
# Runs a command while simulated host stalls hit both CPUs (bench/c/stalls.c: a SCHED_FIFO
# 99 task per CPU that holds it for 0.5..MAX_MS ms every 100..EVERY_MS ms), to see which
# tests a stalling machine breaks before a CI machine does. The stall tasks end with the
# command, also when it fails or is interrupted. Exits with the command's status.
#
#   bash scripts/under-stalls.sh cargo test --workspace --no-fail-fast
#   MAX_MS=20 EVERY_MS=300 bash scripts/under-stalls.sh cargo test --test standby
#
# Needs root (SCHED_FIFO 99) and gcc. Defaults: MAX_MS 8, EVERY_MS 400 on CPU 1 and twice
# that period on CPU 0 (about the stalls of docs/measurements.md, "The host's stalls").
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -gt 0 ] || { echo "usage: bash scripts/under-stalls.sh COMMAND [ARG ...]" >&2; exit 2; }
max_ms=${MAX_MS:-8}
every_ms=${EVERY_MS:-400}
bin=$(mktemp -d)/stalls
gcc -O2 -o "$bin" bench/c/stalls.c
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  wait "${pids[@]}" 2>/dev/null || true
  rm -rf "$(dirname "$bin")"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
"$bin" 1 "$max_ms" "$every_ms" & pids+=($!)
"$bin" 0 "$max_ms" $((every_ms * 2)) & pids+=($!)
sleep 0.2
for p in "${pids[@]}"; do
  kill -0 "$p" 2>/dev/null || { echo "under-stalls: a stall task did not start (root?)" >&2; exit 1; }
done
echo "under-stalls: stalls of up to $max_ms ms every 100..$every_ms ms on CPU 1, 100..$((every_ms * 2)) ms on CPU 0" >&2
# In the background and waited for, so that a signal to this script runs its traps at once
# (the command is stopped with the stall tasks).
"$@" <&0 & pids+=($!)
status=0
wait "${pids[-1]}" || status=$?
exit "$status"
