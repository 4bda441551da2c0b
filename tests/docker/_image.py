"""The rig's image for the docker tier: built once per machine at a time, whoever asks first.

Two tests need it: ``test_image`` (a unit of its own, tests/conftest.py's ``IMAGE_SCOPE``, which
runs on the worker that is not running the live tests) and ``test_compose_up`` (the last of the
live tests). On a clean machine the build -- a debootstrap base, the wheelhouse, the image with
its kernels compiled ahead of time -- made the compose test take 183 s against 47 s with every
layer cached (2026-12-07); made beside the live tests, the live worker's chain no longer waits
for it. Both go through :func:`ensure` under one file lock, so they never build at once (nor two
suites of one user): whoever comes second finds every layer cached and is done in seconds.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import tempfile
import time
from pathlib import Path

from tests.docker import _engine

SRC = Path(os.environ.get("HIL_DOCKER_SRC") or _engine.REPO)  # the checkout to build (default: this one)
IMAGE = "hil:test"
COMPOSE_FILES = ("-f", "docker-compose.yml", "-f", "docker-compose.local-router.yml")
LOCK = Path(tempfile.gettempdir()) / f"hil-docker-image-{os.getuid()}.lock"  # a user's own to open


def build_env(**extra: str) -> dict[str, str]:
    """The environment the image is built (and composed) with: the offline base and wheelhouse."""
    env = dict(os.environ)
    env.update(
        HIL_IMAGE=IMAGE,
        HIL_BASE_IMAGE=os.environ.get("HIL_DOCKER_BASE_IMAGE", "localpy:bookworm"),
        HIL_PIP_OFFLINE="1",
        **extra,
    )
    return env


def run(
    cmd: list[str], env: dict[str, str], timeout: float, check: bool = True
) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(cmd, cwd=SRC, env=env, capture_output=True, text=True, timeout=timeout)
    if check and r.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} -> {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    return r


def ensure() -> dict[str, float]:
    """Build the base image and ``hil:test`` (cached layers make a second call quick); the seconds
    each step took, and how long this call waited for another one's build. Skips (or fails under
    ``HIL_REQUIRE_DOCKER=1``) without an engine or when the base image cannot be made."""
    reason = _engine.engine_reason()
    if reason:
        _engine.unavailable(reason)
    compose = _engine.compose_cmd()
    assert compose is not None
    env = build_env()
    figures: dict[str, float] = {}
    t = time.monotonic()
    with LOCK.open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or when the process dies
        figures["waited_s"] = time.monotonic() - t
        t = time.monotonic()
        base = run(["bash", str(SRC / "deploy/build-base-image.sh")], env, timeout=900, check=False)
        if base.returncode != 0:
            _engine.unavailable(
                f"cannot make the offline base image/wheelhouse: {base.stderr.strip()[-300:]}"
            )
        figures["base_image_s"] = time.monotonic() - t
        t = time.monotonic()
        run([*compose, *COMPOSE_FILES, "build"], env, timeout=900)
        figures["build_s"] = time.monotonic() - t
    return figures
