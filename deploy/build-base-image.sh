#!/usr/bin/env bash
# Offline image prerequisites for machines that reach package registries but no image registry.
#
#   deploy/build-base-image.sh            # base image localpy:bookworm + wheelhouse in deploy/wheels
#
# 1. A Debian bookworm root filesystem made by debootstrap (python3 3.11, venv, iproute2) and
#    imported as the image `localpy:bookworm` -- used instead of python:3.11-slim-bookworm via
#    `--build-arg BASE_IMAGE=localpy:bookworm`.
# 2. A wheelhouse of the runtime dependencies pinned by requirements.lock, downloaded on the host
#    (pip inside a build step cannot verify TLS here), copied into deploy/wheels/ so the Dockerfile
#    installs with `--no-index` (`--build-arg PIP_OFFLINE=1`).
#
# Both are cached under $HIL_CACHE (default /var/cache/hil, or ~/.cache/hil when not root), so a
# rerun takes a second. Needs root (debootstrap) and a running Docker engine.
set -euo pipefail
cd "$(dirname "$0")/.."

BASE_TAG=${HIL_BASE_IMAGE:-localpy:bookworm}
if [ -z "${HIL_CACHE:-}" ]; then
  if [ "$(id -u)" = 0 ]; then HIL_CACHE=/var/cache/hil; else HIL_CACHE=$HOME/.cache/hil; fi
fi
mkdir -p "$HIL_CACHE"
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] && PY=.venv/bin/python

# -- wheelhouse ---------------------------------------------------------------------------------
WHEELS=$HIL_CACHE/wheels
stamp=$(cat requirements.lock deploy/requirements-runtime.txt deploy/requirements-build.txt | sha256sum | cut -c1-16)
if [ ! -f "$WHEELS/.stamp-$stamp" ]; then
  echo "build-base-image: downloading wheels into $WHEELS" >&2
  rm -rf "$WHEELS"; mkdir -p "$WHEELS"
  "$PY" -m pip download -q --disable-pip-version-check -d "$WHEELS" --only-binary=:all: \
    --python-version 3.11 --platform manylinux2014_x86_64 --platform manylinux_2_28_x86_64 \
    --platform manylinux_2_17_x86_64 --implementation cp --abi cp311 --abi abi3 --abi none \
    -c requirements.lock -r deploy/requirements-runtime.txt -r deploy/requirements-build.txt
  touch "$WHEELS/.stamp-$stamp"
fi
# the build context only sees deploy/wheels (ignored by git)
find deploy/wheels -name '*.whl' -delete
cp "$WHEELS"/*.whl deploy/wheels/

# -- base image ---------------------------------------------------------------------------------
if docker image inspect "$BASE_TAG" >/dev/null 2>&1; then
  echo "build-base-image: $BASE_TAG present" >&2
  exit 0
fi
TARBALL=$HIL_CACHE/rootfs-bookworm.tar
if [ ! -s "$TARBALL" ]; then
  # the machine's own Debian mirror (apt's sources), else deb.debian.org
  MIRROR=${DEBIAN_MIRROR:-$(grep -rhoE '^(URIs:|deb) +https?://[^ ]+/debian/?( |$)' /etc/apt/sources.list \
    /etc/apt/sources.list.d/ 2>/dev/null | head -1 | awk '{print $2}' || true)}
  MIRROR=${MIRROR:-http://deb.debian.org/debian}
  ROOTFS=$(mktemp -d "$HIL_CACHE/rootfs.XXXXXX")
  echo "build-base-image: debootstrap bookworm from $MIRROR" >&2
  debootstrap --variant=minbase --include=python3,python3-venv,iproute2,ca-certificates \
    bookworm "$ROOTFS" "$MIRROR" >"$HIL_CACHE/debootstrap.log" 2>&1 \
    || { tail -20 "$HIL_CACHE/debootstrap.log" >&2; rm -rf "$ROOTFS"; exit 1; }
  rm -rf "$ROOTFS"/var/cache/apt/archives/*.deb "$ROOTFS"/var/lib/apt/lists/*
  tar -C "$ROOTFS" -cf "$TARBALL.tmp" . && mv "$TARBALL.tmp" "$TARBALL"
  rm -rf "$ROOTFS"
fi
docker import -c 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  -c 'CMD ["python3"]' "$TARBALL" "$BASE_TAG" >/dev/null
echo "build-base-image: imported $BASE_TAG" >&2
