# One image for every hil service (and, where no image registry is reachable, the Zenoh router).
#
#   docker build -t hil:dev .                                   # users: official slim Python base, PyPI
#   deploy/build-base-image.sh && docker build -t hil:dev \
#     --build-arg BASE_IMAGE=localpy:bookworm --build-arg PIP_OFFLINE=1 .   # offline: debootstrap base + wheelhouse
#
# Dependencies are pinned by requirements.lock (used as constraints), the package is installed
# into /opt/venv in a build stage, and the runtime stage carries only that venv and the repo's
# data files. Services run as the unprivileged user `hil` (uid 10001).
ARG BASE_IMAGE=python:3.11-slim-bookworm

FROM ${BASE_IMAGE} AS build
ARG PIP_OFFLINE=0
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1 PYTHONDONTWRITEBYTECODE=1
WORKDIR /src
COPY requirements.lock pyproject.toml README.md ./
COPY deploy/requirements-runtime.txt deploy/requirements-build.txt deploy/
COPY deploy/wheels/ /wheels/
RUN set -eu; \
    if [ "$PIP_OFFLINE" = 1 ]; then src="--no-index --find-links /wheels"; else src=""; fi; \
    python3 -m venv /opt/venv; \
    /opt/venv/bin/pip install -q $src -c requirements.lock -r deploy/requirements-build.txt; \
    /opt/venv/bin/pip install -q $src -c requirements.lock -r deploy/requirements-runtime.txt
COPY hil/ hil/
COPY services/ services/
RUN set -eu; \
    if [ "$PIP_OFFLINE" = 1 ]; then src="--no-index --find-links /wheels"; else src=""; fi; \
    /opt/venv/bin/pip install -q $src --no-build-isolation --no-deps . ; \
    /opt/venv/bin/python -c "import can, hil.can.zenoh_bus, services.world; can.Bus; print('hil image ok')"
# The fusion's kernels compiled ahead of time (hil.runtime.aot) into the installed package, for
# this machine's CPU: a container then loads them in 0.16 s here, where numba otherwise compiles
# them at every start (11 s of a core here, beside the running fusion). numba's toolchain wants a C
# and a C++ compiler. Best effort: a build that cannot reach Debian's mirror for them, or another
# CPU at run time, gets numba's kernels as before. Run from /tmp: the installed package, not /src.
RUN set -u; \
    cd /tmp; \
    py=/opt/venv/bin/python; \
    inc="$($py -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"; \
    pkgs="gcc g++ libc6-dev"; [ -f "$inc/Python.h" ] || pkgs="$pkgs python3-dev"; \
    if apt-get update -qq >/dev/null 2>&1 \
       && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $pkgs >/dev/null 2>&1; then \
        $py -m hil.runtime.aot --dir "$($py -c 'import hil.runtime, os; print(os.path.join(os.path.dirname(hil.runtime.__file__), "__pycache__"))')" \
            || echo "hil image: the kernels were not built ahead of time; numba compiles them at run time"; \
    else \
        echo "hil image: no C compiler (apt-get could not install $pkgs); numba compiles the kernels at run time"; \
    fi

FROM ${BASE_IMAGE}
ENV PATH=/opt/venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1 NUMBA_CACHE_DIR=/tmp/numba-cache \
    HIL_RIG=bench HIL_SERVICE= \
    HIL_ZENOH_MODE=client HIL_ZENOH_CONNECT=tcp/router:7447
RUN (getent group hil || groupadd --system --gid 10001 hil) \
    && useradd --system --uid 10001 --gid 10001 --home-dir /app --shell /usr/sbin/nologin hil \
    && mkdir -p /data /app \
    && chown hil:hil /data
COPY --from=build /opt/venv /opt/venv
WORKDIR /app
COPY schemas/ schemas/
COPY deploy/healthcheck.py deploy/zenoh/ deploy/
# the package finds its data (imu.dbc, message schemas) next to itself: point that at /app/schemas
RUN ln -s /app/schemas "$(/opt/venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/schemas"
ENV HIL_DBC=/app/schemas/imu.dbc
USER hil
VOLUME ["/data"]
EXPOSE 7447/tcp
# Healthy = this container's service published a live ServiceStatus on hil/<rig>/status/<service>
# (or, for HIL_SERVICE=router, the router accepts a Zenoh session).
HEALTHCHECK --interval=30s --timeout=10s --start-period=20s --retries=3 \
    CMD ["python3", "/app/deploy/healthcheck.py"]
ENTRYPOINT ["hil"]
CMD ["--help"]
