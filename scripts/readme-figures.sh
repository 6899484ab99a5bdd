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
# The cycle latency of each second, read back from the same run's trace.mcap.
./target/release/drivelab plot runs/readme-default --from-mcap --out runs/readme-default/from-mcap
cp runs/readme-default/from-mcap/latency-per-second.png docs/img/mcap-latency-per-second.png
./target/release/drivelab bench --rates 10000,20000 --placements one-core --seconds 20 --rounds 10 --out runs/readme-bench
cp runs/readme-bench/percentiles-10000hz.png docs/img/bench-10khz.png
cp runs/readme-bench/percentiles-20000hz.png docs/img/bench-20khz.png
cp runs/readme-bench/bench.md docs/bench-interleaved.md
./target/release/drivelab run --scenario kyslan-pi --duration 1 --fault kill:current-loop@0.3 --out runs/readme-fault
cp runs/readme-fault/speed.png docs/img/fault-speed.png
cp runs/readme-fault/currents.png docs/img/fault-currents.png
# Plant realism (docs/architecture.md): Low's observer under R +30 %, Miyajima's voltage
# phase with current noise, kyslan-pi behind the switching inverter.
cargo run --release -p drivelab-tools --example plant_realism_figures -- docs/img
rm -f docs/img/low-angle-error-r30.svg docs/img/miyajima-0rpm-noise-phase.svg
./target/release/drivelab run --scenario kyslan-pi-pwm --clock inprocess --out runs/readme-pwm
cp runs/readme-pwm/currents.png docs/img/kyslan-pi-pwm-currents.png
# The monitor's screen (as text) during a drive with a killed current loop, pasted into
# docs/monitor.md between the MONITOR markers.
./target/release/drivelab run --bus readmemon --duration 8 --fault kill:current-loop@3 \
  --no-plots --out runs/readme-monitor >/dev/null 2>&1 &
sleep 6
./target/release/drivelab monitor --bus readmemon --print --print-size 118x30 > docs/img/monitor.txt
wait
python3 - <<'PY'
import re
text = open("docs/img/monitor.txt").read().rstrip("\n")
doc = open("docs/monitor.md").read()
doc = re.sub(r"(<!-- MONITOR -->\n```\n).*?(\n```\n<!-- /MONITOR -->)",
             lambda m: m.group(1) + text + m.group(2), doc, flags=re.S)
open("docs/monitor.md", "w").write(doc)
PY
# The smoke campaign's table, pasted into the README between the SMOKE markers.
./target/release/drivelab campaign campaigns/smoke.toml --out runs/readme-smoke >/dev/null 2>&1 || true
python3 - <<'PY'
import re
lines = open("runs/readme-smoke/campaign.md").read().splitlines()
head = "`campaigns/smoke.toml` on this machine: " + next(l for l in lines if l.endswith("skipped."))
table = head + "\n\n" + "\n".join(l for l in lines if l.startswith("|"))
readme = open("README.md").read()
readme = re.sub(r"(<!-- SMOKE -->\n).*?(<!-- /SMOKE -->)",
                lambda m: m.group(1) + table + "\n" + m.group(2), readme, flags=re.S)
open("README.md", "w").write(readme)
PY
