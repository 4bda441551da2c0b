"""The rig's image as built (``docker compose build``): this checkout's package, an unprivileged
user, the status healthcheck, the CLI as its entry point.

A unit of its own under ``make test`` (tests/conftest.py's ``IMAGE_SCOPE``): it builds the image on
the worker that is not running the live tests, which then find it built (``test_compose_up``,
the last live test, runs the whole stack from it). It starts no container of a rig and opens no
bus: each check is one ``docker run --rm`` or ``docker inspect``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.docker import _image

pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(900)]

# the package's sources in a stable order: one script, run here and in the image
_DIGEST = (
    "import hashlib, pathlib, sys\n"
    "root = pathlib.Path(sys.argv[1])\n"
    "h = hashlib.sha256()\n"
    "for p in sorted(root.rglob('*.py')):\n"
    "    if '__pycache__' in p.parts: continue\n"
    "    h.update(p.relative_to(root).as_posix().encode() + b'\\0' + p.read_bytes() + b'\\0')\n"
    "print(h.hexdigest())\n"
)


@pytest.fixture(scope="module")
def image() -> str:
    figures = _image.ensure()
    print(f"image figures: { {k: round(v, 1) for k, v in figures.items()} }")
    return _image.IMAGE


def _in_image(image: str, *cmd: str, entrypoint: str | None = None) -> str:
    head = ["docker", "run", "--rm"] + (["--entrypoint", entrypoint] if entrypoint else [])
    return _image.run([*head, image, *cmd], _image.build_env(), timeout=120).stdout


def test_the_image_holds_this_checkout_s_package(image: str) -> None:
    """Not a stale layer: the installed ``hil`` package's sources are this checkout's, byte for byte."""
    here = _image.SRC / "hil"
    local = subprocess.run(
        [sys.executable, "-c", _DIGEST, str(here)], capture_output=True, text=True, timeout=60, check=True
    ).stdout.strip()
    where = _in_image(
        image, "-c", "import hil, os; print(os.path.dirname(hil.__file__))", entrypoint="/opt/venv/bin/python"
    ).strip()
    inside = (
        _in_image(image, "-c", _DIGEST, where, entrypoint="/opt/venv/bin/python").strip().splitlines()[-1]
    )
    assert len(local) == 64 and inside == local, f"the image's {where} differs from {here}"


def test_the_image_runs_unprivileged_with_the_status_healthcheck(image: str) -> None:
    uid = _in_image(image, "-u", entrypoint="id").strip()
    assert uid.isdigit() and int(uid) != 0, f"the image runs as uid {uid!r}"
    out = _image.run(
        ["docker", "inspect", "--format", "{{json .Config}}", image], _image.build_env(), timeout=60
    ).stdout
    config = json.loads(out)
    health = (config.get("Healthcheck") or {}).get("Test") or []
    assert any("healthcheck.py" in part for part in health), health
    assert config.get("Entrypoint") == ["hil"], config.get("Entrypoint")
    assert "/data" in (config.get("Volumes") or {}), config.get("Volumes")


def test_the_cli_answers_in_the_image(image: str) -> None:
    """Its entry point is the CLI, and the package finds its data where the image put it: the
    message schemas through the ``schemas`` link beside the package (``hil schemas`` exits 0 only
    when every one is there and matches the message types), the DBC through ``HIL_DBC``."""
    usage = _in_image(image, "--help")
    assert usage.startswith("usage: hil") and "{up,sim," in usage, usage[:500]
    _in_image(image, "schemas")  # a missing or stale schema exits non-zero: _image.run raises
    probe = (
        "from hil.can.codec import ImuCanCodec; print(type(ImuCanCodec.from_dbc(None, fd=False)).__name__)"
    )
    out = _in_image(image, "-c", probe, entrypoint="/opt/venv/bin/python")
    assert out.strip().splitlines()[-1] == "ImuCanCodec", out
