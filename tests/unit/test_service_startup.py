"""What a service process loads before it can say ready (time zero waits for the slowest).

Not timed (a loaded machine stretches any time): the modules themselves. python-can and numpy
are ~0.1 s of CPU each at import; a service that does not use them must not pay for them, and
``hil service`` must parse its command line the same with its own parser alone.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.cli import build_parser
from tests.conftest import REPO

# What `hil service NAME --options ...` does before the service runs, in a fresh interpreter.
_ENTRY = """
import json, sys
from hil.cli import build_parser
a, rest = build_parser(service_only=True).parse_known_args(["service", NAME, "--options", "{}"])
from hil.runtime.registry import service_module
import hil.runtime.service
service_module(a.name)
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in ("numpy", "can", "cantools"))))
"""


def loaded_by(service: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", _ENTRY.replace("NAME", repr(service))],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return {m.split(".")[0] for m in json.loads(out.stdout)}


def test_the_recorder_starts_without_numpy_or_python_can() -> None:
    assert loaded_by("recorder") == set()


def test_the_time_sync_starts_without_numpy_or_python_can() -> None:
    # its core is integer arithmetic on stamps; the scenario and clock configs it reads must not
    # pull numpy in (sensor_specs' GM_PEAK_RATIO, hil.sensors.clock, hil.nodes.builders)
    assert loaded_by("timesync") == set()


@pytest.mark.parametrize("service", ["fusion", "timesync", "world", "gnss_emulator"])
def test_services_without_a_can_bus_start_without_python_can(service: str) -> None:
    loaded = loaded_by(service)
    assert "can" not in loaded and "cantools" not in loaded, loaded


@pytest.mark.parametrize("service", ["can_bridge", "imu_emulator"])
def test_the_dbc_reader_is_loaded_with_the_dbc_not_before(service: str) -> None:
    # the DBC is read when the node is built (the run's announcement), after the service is ready
    loaded = loaded_by(service)
    assert "can" in loaded and "cantools" not in loaded, loaded


def test_hil_service_parses_the_same_with_its_own_parser_alone() -> None:
    argv = ["service", "recorder", "--rig", "r1", "--options", '{"path": "x.mcap"}', "--no-zenoh-advanced"]
    full, rest_full = build_parser().parse_known_args(argv)
    alone, rest_alone = build_parser(service_only=True).parse_known_args(argv)
    assert rest_alone == rest_full == ["--no-zenoh-advanced"]
    drop = {"parser"}  # the subparser object itself: one per build
    assert {k: v for k, v in vars(alone).items() if k not in drop} == {
        k: v for k, v in vars(full).items() if k not in drop
    }
    assert alone.name == "recorder" and alone.options == '{"path": "x.mcap"}' and alone.rig == "r1"


_THREADS = """
import os, sys
import hil.runtime.service
hil.runtime.service.run_service = lambda *a, **k: 0  # the service's entry: not run here
from hil.cli import main
sys.argv = ["hil", *sys.argv[1:]]  # the program itself (main() without arguments), as `hil` runs
main()
import numpy  # a command that did not import it (the service above, run_service replaced)
print(os.environ.get("OPENBLAS_NUM_THREADS"), len(os.listdir("/proc/self/task")))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/task")
@pytest.mark.parametrize(("setting", "threads"), [(None, 1), ("2", 2)])
@pytest.mark.parametrize(
    "command",
    [
        ["service", "fusion", "--rig", "x", "--options", "{}"],
        [
            "sim",
            "--scenario",
            "static",
            "--duration",
            "0.2",
            "--estimators",
            "ins",
            "--record",
            "{tmp}",
            "--quiet",
        ],
    ],
    ids=["service", "sim"],
)
def test_a_hil_process_starts_no_blas_threads_unless_asked(
    setting: str | None, threads: int, command: list[str], tmp_path: Path
) -> None:
    # its matrices are too small for OpenBLAS's threads; starting them costs start-up CPU (a
    # sim's are stopped again when it forks its worker: OpenBLAS's fork handler; its setting for
    # the whole process is what tells)
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if setting is not None:
        env["OPENBLAS_NUM_THREADS"] = setting  # the user's setting wins
    args = [c.replace("{tmp}", str(tmp_path / "s.mcap")) for c in command]
    out = subprocess.run(
        [sys.executable, "-c", _THREADS, *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    setting_seen, n_threads = out.stdout.split()[-2:]
    assert setting_seen == str(threads)
    if command[0] == "service":
        assert int(n_threads) == threads  # the main thread, and OpenBLAS's beyond it


_RERUN_TIMESYNC = """
import json, sys
from hil.cli import main
rc = main(["rerun", "--core", "timesync", "--verify", sys.argv[1]])
print(json.dumps([rc, sorted(m for m in sys.modules if m.split(".")[0] in ("numpy", "foxglove"))]))
"""


def test_the_time_sync_rerun_does_not_import_numpy_or_the_foxglove_sdk() -> None:
    # `hil rerun --core timesync`: numpy's import was ~40 % of a 60 s recording's rerun; the
    # Foxglove SDK came with hil.wellknown, for the prefix of the channels a reader leaves out
    from tests.replay.helpers import GOLDEN

    out = subprocess.run(
        [sys.executable, "-c", _RERUN_TIMESYNC, str(GOLDEN)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "VERIFY OK" in out.stdout, out.stdout
    rc, loaded = json.loads(out.stdout.splitlines()[-1])
    assert rc == 0 and loaded == [], (rc, loaded)


def test_the_readers_copy_of_the_derived_channels_prefix_is_wellknowns() -> None:
    from hil.record.mcapio import DERIVED_PREFIX
    from hil.wellknown import PREFIX

    assert DERIVED_PREFIX == PREFIX


_READER = """
import json, sys
from hil.cli import build_parser
build_parser()  # every command's parser, as `hil <anything>` builds it
import hil.record.mcapio
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in ("numpy", "foxglove", "mcap"))))
"""


def test_the_command_line_and_a_recordings_reader_load_neither_numpy_nor_the_writer_side() -> None:
    # `hil rerun --core timesync`, `hil info`, ...: numpy (~0.1 s), mcap's writer and the Foxglove
    # SDK's schemas (~40 ms) are a tenth of a 60 s time-sync rerun
    out = subprocess.run(
        [sys.executable, "-c", _READER], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    loaded = set(json.loads(out.stdout))
    assert not {m for m in loaded if m.split(".")[0] in ("numpy", "foxglove")}, loaded
    assert "mcap.writer" not in loaded and "mcap.data_stream" in loaded, loaded
