# Sourced by scripts/setup.sh and scripts/cross.sh: `apt_install [APT-GET OPTIONS] PKG...`
# installs Debian packages non-interactively, as root or through sudo, and says in one line
# what it installs; a machine without apt-get, or a user who is not root and has no sudo,
# gets one line naming the packages to install by hand, and a non-zero status.
apt_install() {
  local me=${0##*/} opts=() sudo=()
  while [ $# -gt 0 ] && [ "${1#-}" != "$1" ]; do
    opts+=("$1")
    shift
  done
  if [ "$(id -u)" -ne 0 ]; then
    if ! command -v sudo >/dev/null 2>&1; then
      echo "$me: not root and no sudo: install these Debian packages by hand: $*" >&2
      return 1
    fi
    sudo=(sudo)
  fi
  if ! command -v apt-get >/dev/null 2>&1; then
    echo "$me: no apt-get here: install the equivalents of these Debian packages: $*" >&2
    return 1
  fi
  echo "$me: installing $*" >&2
  "${sudo[@]}" apt-get update -qq
  # env after sudo: sudo's env_reset would drop a variable set before it.
  "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${opts[@]}" "$@" >/dev/null
}
