#!/usr/bin/env bash
# Builds drivelab and runs the default scenario (kyslan-pi, real time, 10 kHz) into
# runs/default/: trace.csv, summary.json, speed/currents/voltages/latency plots (PNG, SVG)
# and the per-service latency histograms (.hgrm).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --run
cargo build --release --workspace --bins
"${CARGO_TARGET_DIR:-target}/release/drivelab" run --out runs/default "$@"
echo "plots and histograms: runs/default/"
