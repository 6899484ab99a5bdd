#!/usr/bin/env bash
# The drive split across two machines at 1, 2, 5 and 10 kHz, against the same topology on
# one machine (docs/measurements.md, "The drive split across machines"). The two machines are
# two network namespaces joined by a veth pair that this script makes and removes; it needs
# root and a release build (cargo build --release). Runs are interleaved: at each rate, one
# machine, then split, ROUNDS times. Prints one line per run: rate, layout, cycle latency
# p50/p99/p99.9 (µs, the plant's: t_k → command k available on the plant's machine),
# deadline misses per million and the samples in the trace.
#
#   sudo scripts/split-rates.sh [SECONDS] [ROUNDS] [RATES]     # defaults 10 2 "1000 2000 5000 10000"
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${1:-10}
rounds=${2:-2}
rates=${3:-1000 2000 5000 10000}
bin=target/release/drivelab
[ -x "$bin" ] || { echo "split-rates: build first: cargo build --release" >&2; exit 1; }
tag=$$
ns=(dlsr${tag}a dlsr${tag}b)
veth=(dvsr${tag}a dvsr${tag}b)
addr=(10.201.0.1 10.201.0.2)
work=$(mktemp -d /tmp/split-rates.XXXXXX)
cleanup() {
  ip netns del "${ns[0]}" 2>/dev/null || true
  ip netns del "${ns[1]}" 2>/dev/null || true
}
trap cleanup EXIT
ip netns add "${ns[0]}"
ip netns add "${ns[1]}"
ip link add "${veth[0]}" type veth peer name "${veth[1]}"
for i in 0 1; do
  ip link set "${veth[$i]}" netns "${ns[$i]}"
  ip -n "${ns[$i]}" addr add "${addr[$i]}/30" dev "${veth[$i]}"
  ip -n "${ns[$i]}" link set "${veth[$i]}" up
  ip -n "${ns[$i]}" link set lo up
done

# kyslan-pi at RATE Hz, speed loop kept at 1 kHz and the filter and current-loop time
# constants legal at the rate (as `drivelab bench` does).
variant() {
  local hz=$1 ts
  ts=$(python3 -c "print(1.0/$hz)")
  sed -e "s/^sample_hz = .*/sample_hz = $hz.0/" \
      -e "s/^speed_divider = .*/speed_divider = $(( hz >= 1000 ? hz / 1000 : 1 ))/" \
      -e "s/^tau_c_s = .*/tau_c_s = $(python3 -c "print(max(2.5e-4, 2*$ts))")/" \
      -e "s/^speed_filter_tau_s = .*/speed_filter_tau_s = $(python3 -c "print(max(1e-4, $ts))")/" \
      scenarios/kyslan-pi.toml > "$work/kyslan-pi-$hz.toml"
}

report() {
  python3 - "$1" "$2" "$3" <<'EOF'
import json, sys
s = json.load(open(sys.argv[3] + "/summary.json"))
c = s["latency_us"]["cycle"]

print(f"{sys.argv[1]:>6} Hz  {sys.argv[2]:<11} cycle p50 {c['p50']:8.1f}  p99 {c['p99']:8.1f}  p99.9 {c['p999']:8.1f} µs"
      f"  misses/M {s['deadline_misses_per_million']:9.0f}  samples {s['samples']}/{s['samples_expected']}")
EOF
}

port=17500
for r in $(seq "$rounds"); do
  for hz in $rates; do
    variant "$hz"
    sc="$work/kyslan-pi-$hz.toml"
    out="$work/one-$hz-$r"
    "$bin" run --scenario "$sc" --duration "$secs" --topology split-hil --bus "sr${tag}o" --out "$out" --no-plots --json > /dev/null || true
    report "$hz" "one machine" "$out"
    port=$((port + 1))
    ep="tcp/${addr[0]}:$port"
    a="$work/sim-$hz-$r"
    b="$work/board-$hz-$r"
    ip netns exec "${ns[0]}" "$bin" run --scenario "$sc" --duration "$secs" --topology split-hil --machine simulator \
      --zenoh-listen "$ep" --bus "sr${tag}a" --out "$a" --no-plots --json > /dev/null &
    sim=$!
    ip netns exec "${ns[1]}" "$bin" run --scenario "$sc" --duration "$secs" --topology split-hil --machine board \
      --zenoh-connect "$ep" --bus "sr${tag}b" --out "$b" --no-plots --json > /dev/null || true
    wait "$sim" || true
    report "$hz" "split" "$a"
  done
done
rm -rf "$work"
