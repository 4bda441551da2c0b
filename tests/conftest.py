"""Shared fixtures: real Zenoh sessions on loopback, leak checks for child processes."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Container, Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def zenoh_hub(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A real Zenoh router on a free loopback port; children are its clients (via env), the layout
    of hil up's embedded hub."""
    from hil.bus.session import BusConfig, open_session

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    hub = open_session(BusConfig(mode="router", listen=(endpoint,), connect=()))
    monkeypatch.setenv("HIL_ZENOH_MODE", "client")
    monkeypatch.setenv("HIL_ZENOH_CONNECT", endpoint)
    monkeypatch.setenv("HIL_ZENOH_LISTEN", "")
    try:
        yield endpoint
    finally:
        hub.close()


def hil_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "hil.cli", *args]


def exchange_with_child(
    bus: Any,
    child: subprocess.Popen[str],
    want: int,
    timeout_s: float,
    credit_every: int = 0,
    credits: int = 0,
) -> tuple[list[Any], str, str]:
    """The parent's side of a two-process python-can test: "go" (id 0x7FF) until the child
    answers, ``want`` frames read (a "got them" 0x7FD after every ``credit_every`` of the first
    ``credits``), then "ack" (0x7FE); returns the frames and the child's stdout and stderr. The
    bus is shut down and a child still running killed and reaped, whatever fails."""
    import can

    got: list[Any] = []
    try:
        deadline = time.time() + timeout_s
        while len(got) < want and time.time() < deadline:
            if not got:  # the child joins the bus when it opens: until then "go" is lost
                bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"go"))
            msg = bus.recv(timeout=0.2)
            if msg is not None:
                got.append(msg)
                if credit_every and len(got) <= credits and len(got) % credit_every == 0:
                    bus.send(can.Message(arbitration_id=0x7FD, is_extended_id=False, data=b"got"))
        bus.send(can.Message(arbitration_id=0x7FE, is_extended_id=False, data=b"ack"))
        out, err = child.communicate(timeout=timeout_s)
    finally:
        bus.shutdown()
        if child.poll() is None:
            child.kill()
            child.wait()
    return got, out, err


def communicate_or_dump(proc: subprocess.Popen[bytes], timeout: float) -> bytes:
    """``proc.communicate(timeout)``'s output; a service that has not exited by then is asked for
    its threads' stacks (SIGUSR1, ``hil.runtime.service.install_signal_handlers``), killed, and
    the failure shows where it was stuck."""
    try:
        return proc.communicate(timeout=timeout)[0] or b""
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        proc.kill()
        out = proc.communicate(timeout=30)[0] or b""
        text = out.decode(errors="replace")[-8000:]
        raise AssertionError(
            f"pid {proc.pid} did not exit within {timeout} s; its output, stacks last:\n{text}"
        ) from None


def run_hil(
    *args: str, timeout: float = 300, cwd: Path | None = None, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    e = dict(os.environ)
    e.update(env or {})
    return subprocess.run(
        hil_cmd(*args), capture_output=True, text=True, timeout=timeout, cwd=cwd or REPO, env=e
    )


def spoof_event_toml(t_start_s: float, t_end_s: float) -> str:
    """A scenario's ``gnss_spoof`` event: 500 m north claiming σ 0.5 m (the tests' one spoof)."""
    return f"""
[[event]]
kind = "gnss_spoof"
t_start_s = {t_start_s}
t_end_s = {t_end_s}
offset_ned_m = [500.0, 0.0, 0.0]
sigma_m = 0.5
"""


SIM_RECORDING_SCENARIO = """
name = "simrec"
seed = 11
duration_s = 3.0

[origin]
lat_deg = 50.45
lon_deg = 30.52
alt_m = 300.0

[initial]
speed_mps = 20.0

[[segment]]
kind = "turn"
duration_s = 3.0
yaw_rate_dps = 10.0

[[event]]
kind = "imu_frame_loss"
t_start_s = 1.0
t_end_s = 1.5
percent = 50.0
"""


@pytest.fixture(scope="session")
def sim_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh 3 s ``hil sim`` recording of a turn with a timed fault (every topic of the rig,
    events and counters), made once per test session."""
    from hil.runners.sim import SimOptions, run_sim

    root = tmp_path_factory.mktemp("sim")
    scenario = root / "simrec.toml"
    scenario.write_text(SIM_RECORDING_SCENARIO)
    path = root / "sim.mcap"
    run_sim(SimOptions(scenario=str(scenario), duration_s=3.0, record=path, rig="simrec", on_warning=print))
    return path


# -- leftovers: every session, thread and process a test opens is closed by its teardown -------
#
# A test that fails half-way must not leave a rig running or a Zenoh session open: an open
# session with a subscriber keeps a non-daemon "pyo3-closure" thread alive, and pytest then never
# exits (it waited 18 minutes in threading._shutdown once). Each test is checked after its own
# teardown (function-scoped fixtures included; module fixtures' sessions and processes, which
# start before it, are not its own): what it left is closed or killed here and the test fails,
# naming it. The session-end check does the same for anything left at the very end and, if a
# non-daemon thread still runs, ends the process so that CI fails instead of hanging.

_OPEN_SESSIONS: list[Any] = []  # every zenoh.Session opened in this process (no weakrefs on them)
_real_zenoh_open = None


def _track_zenoh_sessions() -> None:
    global _real_zenoh_open
    import zenoh

    if _real_zenoh_open is not None:
        return
    _real_zenoh_open = zenoh.open

    def tracked_open(*args: Any, **kwargs: Any) -> Any:
        session = _real_zenoh_open(*args, **kwargs)  # type: ignore[misc]
        _OPEN_SESSIONS.append(session)
        return session

    zenoh.open = tracked_open  # type: ignore[assignment]


_track_zenoh_sessions()


def _open_sessions() -> list[Any]:
    _OPEN_SESSIONS[:] = [s for s in _OPEN_SESSIONS if not s.is_closed()]
    return list(_OPEN_SESSIONS)


def _descendants(known: Container[int] = ()) -> dict[int, str]:
    """Live (not zombie) descendants of this process: pid -> command line.

    ``known`` processes (a module fixture's rig, started before the test) and their subtrees are
    left out: what they start (a supervisor restarting a service) is theirs, not the test's.
    """
    out: dict[int, str] = {}
    todo = [os.getpid()]
    while todo:
        p = todo.pop()
        try:
            tasks = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for t in tasks:
            try:
                kids = Path(f"/proc/{p}/task/{t}/children").read_text().split()
            except OSError:
                continue
            for k in map(int, kids):
                if k in known:
                    continue
                try:
                    state = Path(f"/proc/{k}/stat").read_text().rsplit(")", 1)[1].split()[0]
                    cmd = (
                        Path(f"/proc/{k}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                    )
                except OSError:
                    continue
                if state != "Z":
                    out[k] = cmd.strip()[:160]
                todo.append(k)
    return out


def _live_threads() -> set[threading.Thread]:
    return {
        t for t in threading.enumerate() if t.is_alive() and not t.daemon and t is not threading.main_thread()
    }


def _clean_up(
    procs: dict[int, str], sessions: list[Any], threads: set[threading.Thread], grace_s: float
) -> list[str]:
    """Wait up to ``grace_s`` for what is still closing; then close, kill and say what was left."""
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and (_descendants(procs.keys()) or _live_threads() - threads):
        time.sleep(0.1)
    problems: list[str] = []
    left_sessions = [s for s in _open_sessions() if all(s is not b for b in sessions)]
    if left_sessions:
        problems.append(f"{len(left_sessions)} Zenoh session(s) left open (closed now)")
        for s in left_sessions:
            with contextlib.suppress(Exception):
                s.close()
    left = _descendants(procs.keys())
    if left:
        problems.append(
            "process(es) left running (killed now): " + "; ".join(f"{p} {c}" for p, c in left.items())
        )
        for p in left:
            with contextlib.suppress(OSError):
                os.kill(p, signal.SIGKILL)
    time.sleep(0.2 if left_sessions else 0)
    extra = [t.name for t in _live_threads() - threads]
    if extra:
        problems.append(f"non-daemon thread(s) left running: {', '.join(extra)}")
    return problems


# how long a test's children and threads may take to end after its teardown (only spent when one
# is still there: a clean test costs ~0.5 ms for the whole check)
_GRACE_S = float(os.environ.get("HIL_TEST_LEFTOVER_GRACE_S", "5"))


def _signal_handlers() -> dict[str, Any]:
    return {name: signal.getsignal(getattr(signal, name)) for name in ("SIGINT", "SIGTERM")}


@pytest.fixture(autouse=True)
def _no_leftovers(request: pytest.FixtureRequest) -> Iterator[None]:
    procs, sessions, threads = _descendants(), _open_sessions(), _live_threads()
    handlers = _signal_handlers()
    yield
    problems = _clean_up(procs, sessions, threads, grace_s=_GRACE_S)
    changed = [
        f"{name} handler {handlers[name]!r} -> {h!r}"
        for name, h in _signal_handlers().items()
        if h != handlers[name]
    ]
    if changed:  # code run in-process must give the signals back: a library user's Ctrl-C too
        for name, h in handlers.items():
            signal.signal(getattr(signal, name), h)
        problems += changed
    if problems:
        pytest.fail(f"{request.node.nodeid} left behind: " + " | ".join(problems), pytrace=False)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    problems = _clean_up({}, [], set(), grace_s=2.0)
    if problems:
        sys.stderr.write("\n\nLEFTOVERS AT THE END OF THE TEST SESSION: " + " | ".join(problems) + "\n")
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.hookimpl(trylast=True)  # after the other plugins' (junitxml writes its report there)
def pytest_unconfigure(config: pytest.Config) -> None:
    stuck = _live_threads()
    if stuck:  # Python would wait for them forever in threading._shutdown: fail now instead
        sys.stderr.write(
            f"\nnon-daemon threads still running at exit: {[t.name for t in stuck]}; exiting 1\n"
        )
        sys.stderr.flush()
        sys.stdout.flush()
        os._exit(1)


#: Tests that start rigs, containers or network namespaces run one at a time on one
#: pytest-xdist worker (``make test`` runs ``-n 2``): two live rigs at once would measure each
#: other. The pure tests (unit, replay) fill the other worker meanwhile, which shortens the suite
#: by their time. A scheduler of our own rather than ``--dist loadgroup`` with marks: xdist 3.8
#: renames grouped tests through ``item._nodeid``, which pytest 9's nodes no longer read, so
#: loadgroup silently spread the live tests over both workers.
SERIAL_SCOPE = "live"
POOLED_DIRS = ("unit", "replay")
#: The vcan tier goes to a worker as one unit of its own, beside the live tests: inside
#: user-mode-linux one boot runs all of it (tests/vcan/conftest.py) in a kernel with its own
#: network, and on a real vcan0 no live test touches that device (theirs is the Zenoh CAN
#: transport). In the live unit it had added its ~56 s (the boot and one slow vCPU) to the longest
#: worker's chain, while the other worker had finished its pooled tests and waited.
VCAN_SCOPE = "vcan"
#: The rig's image is built in a unit of its own too (tests/docker/test_image.py: ``docker
#: compose build``, no container of a rig, no bus), on the worker the live tests leave free; the
#: compose test that runs the image is moved to the end of the live unit
#: (``pytest_collection_modifyitems``), so it finds the image built. On a clean machine the build
#: had made that test, the live unit's first, 183 s long against 47 s with the layers cached.
IMAGE_SCOPE = "docker-image"
IMAGE_MODULE = "tests/docker/test_image.py"
LAST_LIVE_MODULES = ("tests/docker/test_compose_up.py",)
#: Modules outside ``POOLED_DIRS`` that start no rig and open no Zenoh session (offline ``hil``
#: runs, a headless browser): pooled as one unit each, so that a module fixture runs once.
POOLED_MODULES = (
    "tests/integration/test_record_tools.py",
    "tests/integration/test_report_browser.py",
    "tests/integration/test_sim_faults.py",
    "tests/integration/test_timesync_startup_step.py",
)


def xdist_scope(nodeid: str) -> str:
    """The unit xdist hands a worker: one pooled test, a pooled module, the vcan tier, or every
    live test together."""
    module = nodeid.split("::", 1)[0]
    parts = module.split("/")
    if len(parts) > 2 and parts[0] == "tests" and parts[1] in POOLED_DIRS:
        return nodeid
    if module in POOLED_MODULES:
        return module
    if len(parts) > 2 and parts[:2] == ["tests", "vcan"]:
        return VCAN_SCOPE
    if module == IMAGE_MODULE:
        return IMAGE_SCOPE
    return SERIAL_SCOPE


def last_live_last(nodeids: list[str]) -> list[int]:
    """The order to run tests in (indices into ``nodeids``): as collected, but the tests of
    ``LAST_LIVE_MODULES`` after all the others, in their own order."""
    late = {i for i, n in enumerate(nodeids) if n.split("::", 1)[0] in LAST_LIVE_MODULES}
    return [i for i in range(len(nodeids)) if i not in late] + sorted(late)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    order = last_live_last([item.nodeid for item in items])
    items[:] = [items[i] for i in order]


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    from xdist.scheduler import LoadScopeScheduling

    class LiveSerialScheduling(LoadScopeScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            return xdist_scope(nodeid)

    return LiveSerialScheduling(config, log)


def pytest_terminal_summary(terminalreporter: Any) -> None:
    """The figures the vcan tests recorded (``record_property``). Here, not in tests/vcan's
    conftest: under xdist the controller, which writes the summary, loads only this one."""
    lines, where = [], f"kernel {os.uname().release}"
    for rep in terminalreporter.getreports("passed") + terminalreporter.getreports("failed"):
        props = getattr(rep, "user_properties", [])
        if "tests/vcan/" not in rep.nodeid:
            continue
        if ("ran_in", "user-mode-linux") in props:
            where = "inside user-mode-linux"
        shown = [p for p in props if p[0] != "ran_in"]
        if shown:
            lines.append(f"{rep.nodeid}: " + ", ".join(f"{k}={v}" for k, v in shown))
    if lines:
        terminalreporter.section(f"vcan figures ({where})")
        for line in lines:
            terminalreporter.write_line(line)
