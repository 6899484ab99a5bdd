#!/usr/bin/env bash
# The cycle latency of `drivelab run --duration 10` with and without a connected Foxglove
# client (docs/measurements.md), interleaved: N rounds of one run without --foxglove, one
# with --foxglove and a client subscribed to every channel (the foxglove_watch example).
# Prints one line per run: cycle p50 / p99 / p99.9 / max µs, deadline misses, messages.
# Run as root on a machine as idle as you can get. Usage: scripts/foxglove-latency.sh [N] [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
rounds=${1:-5}
out=${2:-runs/foxglove-latency}
cargo build --release -p drivelab-services --bin drivelab --example foxglove_watch
bin=target/release/drivelab
watch=target/release/examples/foxglove_watch
mkdir -p "$out"
line() {
  python3 - "$1/summary.json" "$2" <<'EOF'
import json, sys
s = json.load(open(sys.argv[1]))
c = s["latency_us"]["cycle"]
load = open("/proc/loadavg").read().split()[0]
print("%10s cycle p50 %.1f p99 %.1f p99.9 %.1f max %.1f us, misses %d, load %s"
      % (sys.argv[2], c["p50"], c["p99"], c["p999"], c["max"], s["deadline_misses"], load))
EOF
}
for i in $(seq 1 "$rounds"); do
  "$bin" run --duration 10 --no-plots --bus fgl$$ --out "$out/none-$i" >/dev/null 2>&1
  line "$out/none-$i" "none-$i"
  "$bin" run --duration 10 --no-plots --bus fgl$$ --foxglove 127.0.0.1:8765 --out "$out/client-$i" >/dev/null 2>&1 &
  run=$!
  "$watch" 127.0.0.1:8765 > "$out/client-$i.watch.txt"
  wait "$run"
  line "$out/client-$i" "client-$i"
  sed 's/^/           /' "$out/client-$i.watch.txt"
done
