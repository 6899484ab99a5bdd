#!/usr/bin/env bash
# Regenerates the figures shown in the README (docs/img/): the default scenario's plots
# and the bench's 10 kHz percentile chart. Run as root on an otherwise idle machine.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --release --workspace --bins
mkdir -p docs/img
./target/release/drivelab run --out runs/readme-default
for f in speed currents voltages latency; do cp "runs/readme-default/$f.png" "docs/img/$f.png"; done
./target/release/drivelab bench --rates 10000 --seconds 10 --out runs/readme-bench
cp runs/readme-bench/percentiles-10000hz.png docs/img/bench-10khz.png
cp runs/readme-bench/bench.md docs/bench-10khz.md
./target/release/drivelab run --scenario kyslan-pi --duration 1 --fault kill:current-loop@0.3 --out runs/readme-fault
cp runs/readme-fault/speed.png docs/img/fault-speed.png
cp runs/readme-fault/currents.png docs/img/fault-currents.png
