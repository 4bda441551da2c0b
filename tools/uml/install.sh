#!/bin/sh
# Install what the vcan test tier needs on a Debian/Ubuntu host without SocketCAN in its kernel:
# user-mode-linux (a kernel with the CAN modules, run as a process), kmod (insmod), can-utils
# (candump/cansend for interop). Idempotent; needs root. Called by CI before `pytest -m vcan`.
set -eu
need=""
command -v linux >/dev/null 2>&1 || need="$need user-mode-linux"
command -v insmod >/dev/null 2>&1 || need="$need kmod"
command -v candump >/dev/null 2>&1 || need="$need can-utils"
if [ -z "$need" ]; then
    echo "uml/install: user-mode-linux, kmod, can-utils already installed"
    exit 0
fi
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
# shellcheck disable=SC2086
$SUDO apt-get install -y -qq $need
echo "uml/install: installed$need"
