#!/usr/bin/env bash
# Installs what drivelab needs beyond the Rust toolchain, only if it is missing. To build and
# run a drive (`--run`, what scripts/run-default.sh asks for): a C compiler (a few crates
# build C code), pkg-config, fontconfig headers and a TrueType font (plotters draws its
# labels with them). For the tests, also: tmux (the monitor's terminal test runs it),
# rt-tests (cyclictest: `drivelab bench` cross-checks its floor against it), openssl (the
# Zenoh TLS test's certificates), iproute2 (the split drive's test makes network
# namespaces), procps (pgrep, pkill), and a project-local Python environment, .venv/
# (git-ignored), with the `mcap` package from PyPI (the test that reads trace.mcap with a
# reader drivelab did not write); and, if it can, what the aarch64 and armv7 cross builds
# need (scripts/cross.sh --tools-only). Idempotent; changes no kernel setting.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/lib/apt.sh
run_only=0
if [ "${1:-}" = "--run" ]; then run_only=1; fi
if ! command -v cargo >/dev/null 2>&1; then
  echo "setup: cargo is not installed; install the Rust toolchain (rustup) first" >&2
  exit 1
fi
need=()
command -v cc >/dev/null 2>&1 || need+=(gcc g++ libc6-dev)
command -v pkg-config >/dev/null 2>&1 || need+=(pkg-config)
if ! pkg-config --exists fontconfig 2>/dev/null && [ ! -f /usr/include/fontconfig/fontconfig.h ]; then
  need+=(libfontconfig1-dev)
fi
# Counted, not `grep -q`: an early exit of the reader would fail fc-list's write (pipefail).
if [ ! -f /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf ] && [ "$(fc-list 2>/dev/null | wc -l)" -eq 0 ]; then
  need+=(fonts-dejavu-core)
fi
if [ "$run_only" -eq 0 ]; then
  # tmux drives the terminal-UI test of `drivelab monitor`.
  command -v tmux >/dev/null 2>&1 || need+=(tmux)
  # cyclictest, the reference latency tool, measures beside the bench's floor.
  command -v cyclictest >/dev/null 2>&1 || need+=(rt-tests)
  # openssl makes the certificates of the Zenoh TLS example (scripts/zenoh-certs.sh, tested).
  command -v openssl >/dev/null 2>&1 || need+=(openssl)
  # ip makes the split drive's network namespaces; pgrep and pkill find the tests' processes.
  command -v ip >/dev/null 2>&1 || need+=(iproute2)
  command -v pgrep >/dev/null 2>&1 || need+=(procps)
  # python3 with venv and pip (Debian splits them out) for .venv below.
  command -v python3 >/dev/null 2>&1 || need+=(python3)
  if ! python3 -c 'import ensurepip, venv' >/dev/null 2>&1; then need+=(python3-venv); fi
fi
if [ ${#need[@]} -gt 0 ]; then
  apt_install "${need[@]}"
fi
[ "$run_only" -eq 0 ] || exit 0
# The mcap reader of tests/mcap.rs, pinned, in .venv at the repository's root.
MCAP_PY=1.6.0
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
if ! .venv/bin/python -c "import importlib.metadata as m, sys; sys.exit(m.version('mcap') != '$MCAP_PY')" >/dev/null 2>&1; then
  echo "setup: installing mcap==$MCAP_PY into .venv" >&2
  .venv/bin/python -m pip install --quiet --disable-pip-version-check "mcap==$MCAP_PY"
fi
# The ARM builds that tests/cross.rs makes and runs under qemu-user (their lockstep traces
# must equal the x86_64 ones): the Rust targets from rustup, Debian's cross compilers and
# qemu-user, through scripts/cross.sh. Best effort: where one cannot be installed (rustup's
# server out of reach, say) this says so in one line, and so does each test that needs it.
for target in aarch64-unknown-linux-gnu armv7-unknown-linux-gnueabihf; do
  if ! bash scripts/cross.sh --tools-only "$target"; then
    echo "setup: the $target cross build's tools could not be installed; tests/cross.rs will say it did not run it" >&2
  fi
done
