#!/usr/bin/env bash
# Soak run: a real-time drive with random kills throughout, and what the whole drive holds
# while it runs. Every INTERVAL seconds it writes one line to OUT/soak.csv: the resident
# memory of the launcher and of every stage host (MiB, summed as PSS: a page shared by
# several processes, the bus's shared memory, counts once), their open file descriptors,
# and the bus's shared-memory files. Prints the first and the last line.
#
#   bash scripts/soak.sh                      # 1 h, one kill every 30 s on average
#   bash scripts/soak.sh 600 20 runs/soak10   # 10 min, 20 kills, into runs/soak10
#
# Needs target/release/drivelab (scripts/run-default.sh builds it).
set -euo pipefail
cd "$(dirname "$0")/.."
duration=${1:-3600}
kills=${2:-$((duration / 30))}
out=${3:-runs/soak}
interval=${INTERVAL:-30}
bin=target/release/drivelab
[ -x "$bin" ] || { echo "soak: $bin is missing; run: cargo build --release" >&2; exit 1; }
bus="soak$$"
mkdir -p "$out"
"$bin" run --duration "$duration" --fault "random:$kills" --fault-seed 7 --bus "$bus" \
  --out "$out/run" --no-plots >"$out/drive.log" 2>&1 &
launcher=$!
trap 'kill $launcher 2>/dev/null || true' INT TERM
echo "t_s,processes,pss_mib,fds,shm_files" >"$out/soak.csv"
start=$(date +%s)
sample() {
  local pids rss=0 fds=0 n=0 kb
  pids="$launcher $(pgrep -P "$launcher" || true)"
  for p in $pids; do
    kb=$(awk '/^Pss:/ {print $2}' "/proc/$p/smaps_rollup" 2>/dev/null || true)
    [ -n "$kb" ] || continue
    rss=$((rss + kb))
    fds=$((fds + $(ls "/proc/$p/fd" 2>/dev/null | wc -l)))
    n=$((n + 1))
  done
  local shm
  shm=$(find /dev/shm -maxdepth 1 -name "iox2_dl${bus}_*" 2>/dev/null | wc -l)
  echo "$(($(date +%s) - start)),$n,$((rss / 1024)),$fds,$shm" >>"$out/soak.csv"
}
sleep 5
while kill -0 "$launcher" 2>/dev/null; do
  sample
  sleep "$interval"
done
status=0
wait "$launcher" || status=$?
echo "soak: drive exited with $status; first and last samples (t_s,processes,pss_mib,fds,shm_files):"
sed -n 2p "$out/soak.csv"
tail -n 1 "$out/soak.csv"
echo "soak: shared-memory files left: $(find /dev/shm -maxdepth 1 -name "iox2_dl${bus}_*" | wc -l)"
exit "$status"
