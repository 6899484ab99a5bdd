#!/usr/bin/env bash
# Builds drivelab for an ARM board: the stage host (drivelab-host) and the launcher
# (drivelab), without figures and without the monitor's terminal UI (cargo features `plot`
# and `tui`, off here; add `--features tui` to keep the monitor). Installs what is missing
# first, and only that: the Rust target, Debian's cross compiler, qemu-user (to try the
# binaries on this machine; no binfmt handler is registered, qemu-user-binfmt is not
# installed). Then writes target/TARGET/dist/ with the stripped binaries and the scenarios:
# copy that folder to the board.
#
#   scripts/cross.sh aarch64-unknown-linux-gnu           # i.MX 8, AM62, Zynq MPSoC, Pi 3/4/5
#   scripts/cross.sh armv7-unknown-linux-gnueabihf       # 32-bit Cortex-A boards
#   scripts/cross.sh aarch64-unknown-linux-gnu --features tui
#   scripts/cross.sh aarch64-unknown-linux-gnu --features zenoh   # drivelab run --zenoh-listen
#
# The Zenoh bridge (cargo feature `zenoh`, docs/remote.md) is off here like the other
# features; it builds ring (C) with the same cross compiler. drivelab-host never links it.
#
# The linker and the qemu runner of each target are in .cargo/config.toml.
#
#   scripts/cross.sh --tools-only aarch64-unknown-linux-gnu   # install only, build nothing
#                                                             # (scripts/setup.sh does this)
set -euo pipefail
cd "$(dirname "$0")/.."
usage="usage: scripts/cross.sh [--tools-only] aarch64-unknown-linux-gnu|armv7-unknown-linux-gnueabihf [CARGO BUILD ARGS...]"
tools_only=0
if [ "${1:-}" = "--tools-only" ]; then
  tools_only=1
  shift
fi
[ $# -ge 1 ] || { echo "$usage" >&2; exit 2; }
target=$1
shift
case "$target" in
  aarch64-unknown-linux-gnu) gnu=aarch64-linux-gnu qemu=qemu-aarch64 ;;
  armv7-unknown-linux-gnueabihf) gnu=arm-linux-gnueabihf qemu=qemu-arm ;;
  *) echo "cross: unknown target '$target'; $usage" >&2; exit 2 ;;
esac

# Debian's cross compiler and qemu-user first: they do not depend on rustup's server.
need=()
command -v "$gnu-gcc" >/dev/null 2>&1 || need+=("g++-$gnu")
command -v "$qemu" >/dev/null 2>&1 || need+=(qemu-user)
if [ ${#need[@]} -gt 0 ]; then
  source scripts/lib/apt.sh
  # No recommends: qemu-user recommends qemu-user-binfmt, which registers binfmt handlers.
  apt_install --no-install-recommends "${need[@]}"
fi
if ! command -v rustup >/dev/null 2>&1; then
  echo "cross: rustup is not installed; install the Rust toolchain with rustup first" >&2
  exit 1
fi
if ! rustup target list --installed | grep -x "$target" >/dev/null; then
  echo "cross: adding the Rust target $target" >&2
  # rustup's server may be out of reach: give up after 10 minutes rather than hang.
  timeout 600 rustup target add "$target"
fi
[ "$tools_only" -eq 0 ] || exit 0

cargo build --release --target "$target" --no-default-features \
  -p drivelab-runtime --bin drivelab-host -p drivelab-services --bin drivelab "$@"

bin="target/$target/release"
dist="target/$target/dist"
rm -rf "$dist"
mkdir -p "$dist"
for b in drivelab drivelab-host; do
  "$gnu-strip" -o "$dist/$b" "$bin/$b"
done
# drivelab finds scenarios/ beside its executable.
cp -r scenarios "$dist/"
echo "cross: $dist (copy it to the board; stripped sizes):"
for b in drivelab drivelab-host; do
  awk -v b="$b" -v s="$(stat -c %s "$dist/$b")" 'BEGIN { printf "  %-14s %5.1f MB\n", b, s / 1e6 }'
done
cat <<EOF
On the board, in the copied folder: ./drivelab doctor && ./drivelab run --out runs/b1
Here, under qemu: $qemu -L /usr/$gnu $dist/drivelab run --clock lockstep --no-rt \\
                    --runner '$qemu -L /usr/$gnu' --out runs/ls
EOF
