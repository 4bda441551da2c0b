"""``hil up``: every service as its own OS process, one live table, a clean stop, a summary.

The supervisor opens the rig's embedded Zenoh hub (a router listening on a free loopback port; the
services are its clients) and hands its endpoint to every child, so the rig needs no separate
router and no set-up. The hub checks a secret made for the run (``hil.bus.endpoint``: the
children and the user's viewers read it from files only the user can read), so no other process
on the machine can join unless ``--open-bus`` says so. With ``HIL_ZENOH_MODE=client`` or
``HIL_ZENOH_CONNECT`` in the environment it joins that network instead.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
import zenoh

from hil.bus.endpoint import RigAccess, remove_stale_run_files
from hil.bus.identity import RIG_KEY_ENV, ZENOH_ID_ENV, new_rig_key, rig_key_from_env, rig_zid
from hil.bus.keys import Keys
from hil.bus.pubsub import MISS_DETECTION_ENV, Publisher, Stats, Subscriber, deliver_sample
from hil.bus.session import BusConfig, open_session, use_rig_runtime
from hil.messages import Event, FaultCommand, NavSolution, RunInfo, ServiceStatus, Truth
from hil.record.mcapio import restart_part_path
from hil.runners.pacing import RIG_CPUS_ENV, pin_process, unpin_process
from hil.runtime.clock import RigClock
from hil.runtime.options import fill_options
from hil.runtime.registry import SERVICES, STOP_STAGES
from hil.runtime.signals import EventSetter

_N = TypeVar("_N", int, float)


def proc_cpu_seconds(pid: int, tree: bool = True) -> float | None:
    """user + system CPU seconds of a live process (Linux /proc); None where unavailable.
    ``tree``: with its live child processes' (a service's CAN sender process is its own)."""
    return _over_tree(pid, _own_cpu_of, tree)


def proc_wakeups(pid: int, tree: bool = True) -> int | None:
    """How often a live process's threads blocked and were woken again: their voluntary context
    switches (Linux ``/proc/<pid>/task/*/status``), None where unavailable. On a VM each costs
    tens of µs of CPU (docs/benchmarks.md, session 40), so a rig's count says where its CPU goes
    beside the work itself. ``tree``: with its live child processes'. A thread that has ended is
    no longer counted: the rig's threads live as long as their process."""
    return _over_tree(pid, _own_wakeups_of, tree)


@dataclass(frozen=True)
class Usage:
    """What a process spent: CPU seconds (user + system) and wake-ups (voluntary context
    switches), counted together from one base (time zero, or a life's start)."""

    cpu_s: float = 0.0
    wakeups: int = 0

    def __add__(self, other: Usage) -> Usage:
        return Usage(self.cpu_s + other.cpu_s, self.wakeups + other.wakeups)

    def since(self, base: Usage) -> Usage:
        """Spent after ``base``; never negative (a successor's count starts again at 0)."""
        return Usage(max(0.0, self.cpu_s - base.cpu_s), max(0, self.wakeups - base.wakeups))


def proc_usage(pid: int) -> Usage | None:
    """A live process's and its live children's :class:`Usage`; None where /proc has no CPU for it."""
    cpu = proc_cpu_seconds(pid)
    return None if cpu is None else Usage(cpu, proc_wakeups(pid) or 0)


def _over_tree(pid: int, own: Callable[[int], _N | None], tree: bool) -> _N | None:
    """``own(pid)``, with every live descendant's added when ``tree``; None where unavailable."""
    value = own(pid)
    if value is None or not tree:
        return value
    for kid in _children(pid):
        extra = _over_tree(kid, own, True)
        if extra is not None:  # (a child that ended meanwhile)
            value += extra
    return value


def _own_cpu_of(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def _own_wakeups_of(pid: int) -> int | None:
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    n = 0
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/status") as fh:
                for line in fh:
                    if line.startswith("voluntary_ctxt_switches:"):
                        n += int(line.split()[1])
                        break
        except (OSError, ValueError, IndexError):
            continue  # a thread that ended meanwhile
    return n


def _children(pid: int) -> list[int]:
    out: list[int] = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/children") as fh:
                out += [int(x) for x in fh.read().split()]
        except (OSError, ValueError):
            continue
    return out


READY_STATES = ("waiting_run", "running")  # what world waits for before it picks time zero


DUT_EMULATORS = ("unit", "truth")
DUT_UNIT = "dut"  # the child that runs a unit's own program (``--dut-emulator``): not a service


def dut_program(mapping: str) -> Path:
    """The unit's own program a DUT mapping names (``program = "navbox.py"``, next to it)."""
    import tomllib

    p = Path(mapping)
    try:
        with open(p, "rb") as fh:
            program = tomllib.load(fh).get("program")
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise ValueError(f"--dut {p}: cannot read it: {err}") from None
    if not program:
        raise ValueError(
            f'--dut {p} names no unit program (program = "unit.py"); use --dut-emulator truth '
            "for the truth+noise stand-in"
        )
    path = (p.parent / str(program)).resolve()
    if not path.is_file():
        raise ValueError(f"--dut {p}: its program {path} does not exist")
    return path


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _remove_stale_can_dirs(runtime: Path) -> None:
    """The CAN directories (``<rig>-<pid>.can``) of runs that were killed: their process is gone."""
    from hil.bus.endpoint import pid_alive, run_pid
    from hil.can.local_bus import remove_can_dir

    for d in runtime.glob("*-*.can"):
        pid = run_pid(d)
        if pid is not None and not pid_alive(pid):
            remove_can_dir(d)


@dataclass
class UpOptions:
    scenario: str = "straight_level"
    duration_s: float | None = 60.0
    speed: float = 1.0
    record: Path | None = None
    rig: str = "bench"
    channel: str = "vcan0"
    interface: str | None = None  # python-can interface of the IMU and the bridge
    fd: bool = False
    # pacing of the IMU's frames (hil.runners.pacing): real-time priority and CPUs of its sender
    # thread, and what a sample whose tick the host missed does
    rt_priority: int = 0
    cpu_affinity: list[int] = field(default_factory=list)
    sched_slice_us: int = 100  # its time slice at normal priority (hil.runners.pacing.short_slice)
    # the CPUs of every other process of the rig, the hub included (empty: any); with the
    # sender's cpu_affinity elsewhere, the sender has a CPU of its own
    rig_cpus: list[int] = field(default_factory=list)
    late_policy: str = "send"
    estimators: list[str] = field(default_factory=list)
    feedback: str = "auto"  # seed estimators in feedback form (hil.nodes.fusion.FusionOptions)
    ekf_calibration: str = "auto"  # ekf15's calibration states (same)
    # the fusion horizon's lag and its output predictor (same; hil sim's --fusion-lag and
    # --no-output-predictor): None, the fusion's default lag
    lag_s: float | None = None
    output_predictor: bool = True
    # time sync's and the fusion's input batching window (hil.nodes.base.BatchedInputOptions)
    input_batch_ms: float = 0.0
    # the CAN bridge's read window (hil.nodes.can_bridge.CanBridgeOptions.can_batch_ms), ms;
    # None: by the IMU's rate (hil.nodes.can_bridge.read_window_ms)
    can_batch_ms: float | None = None
    live: bool = True
    log_dir: Path | None = None
    restart: int = 0  # restarts allowed per service (0: a death ends the run)
    imu_rate_hz: int | None = None  # override the scenario's IMU rate (soak/load benches)
    dut_mapping: str | None = None  # a device under test on the IMU's CAN bus (can_bridge decodes it)
    # play the unit too: "unit" runs the mapping's own program (``program = ...``, e.g.
    # examples/dut/navbox.py) on the wires; "truth" the truth+noise stand-in (dut_emulator)
    dut_emulator: str | None = None
    restart_ready_s: float = 60.0  # a restarted service not "running" within this is a failed run
    split_mb: float = 0.0  # the recorder starts a new part after this many MB (0: one file)
    split_s: float = 0.0  # ... or after this many seconds
    zenoh_miss_detection: bool = True  # advanced publishers + the recorder's sample-miss listener
    open_bus: bool = False  # the embedded hub without the per-run credential (hil.bus.endpoint)
    # the GNSS receiver on a wire (hil/wire, hil/nodes/gnss_bridge.py)
    gnss_protocol: list[str] = field(default_factory=list)  # nmea, ubx; empty: fixes on Zenoh only
    gnss_serial: str | None = None  # a pseudo-terminal linked at this path, for a device or gpsd
    gnss_tcp: str | None = None  # the same line served over TCP, HOST:PORT
    gnss_baud: int = 115200
    gnss_messages: list[str] = field(default_factory=list)  # the receiver's message set (empty: defaults)
    foxglove: str | None = None  # HOST:PORT: serve the rig to Foxglove (``hil foxglove``, its own process)
    record_include: list[str] = field(default_factory=list)  # recorder key expressions (hil.record.keyfilter)
    record_exclude: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.dut_emulator not in (None, *DUT_EMULATORS):
            raise ValueError(f"dut_emulator {self.dut_emulator!r}: use one of {DUT_EMULATORS}")
        if self.dut_emulator == "unit" and not self.gnss_protocol:
            self.gnss_protocol = ["nmea"]  # the unit reads its receiver off a wire

    @property
    def gnss_wire(self) -> bool:
        return bool(self.gnss_protocol)


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    log_fh: IO[bytes]
    stopping: bool = False
    restarts: int = 0
    final: Usage | None = None  # its CPU and wake-ups at its end (from wait4's rusage)


class LiveView:
    """Status, truth and solutions of one rig, and the compact table ``hil up`` and ``hil monitor`` draw.

    Fed by Zenoh callbacks (``on_*``); ``table()`` renders under the lock. ``alive`` (service ->
    process alive) comes from the supervisor; a remote monitor has no processes and judges a
    service by the age of its last status instead (``STALE_S``).
    """

    STALE_S = 3.0
    TRUTH_MATCH_NS = 20_000_000  # a solution is compared with a truth sample at most this far apart

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.status: dict[str, ServiceStatus] = {}
        self.status_seen: dict[str, float] = {}  # service -> monotonic time of its last status
        self.run: RunInfo | None = None
        self.truth: deque[Truth] = deque(maxlen=400)
        self.errors_m: dict[str, float] = {}
        self.nav_seen: dict[str, float] = {}
        self.ready_at: dict[str, float] = {}  # service -> monotonic time it first said it was ready
        self.nav_last: dict[str, NavSolution] = {}  # compared with truth when the table is drawn
        self.degraded: dict[str, str] = {}  # service -> why, once it has said "degraded"

    def on_status(self, st: ServiceStatus, _k: str) -> None:
        with self.lock:
            self.status[st.service] = st
            self.status_seen[st.service] = time.monotonic()
            if st.state in READY_STATES:
                self.ready_at.setdefault(st.service, self.status_seen[st.service])
            if st.state == "degraded":  # kept: a later "stopping" status does not undo it
                reason = st.last_error or self.degraded.get(st.service) or "no reason given"
                self.degraded[st.service] = reason

    def degraded_since(self, seen: set[str]) -> list[tuple[str, str]]:
        """(service, reason) of every service that said "degraded", but those in ``seen``."""
        with self.lock:
            return [(n, r) for n, r in self.degraded.items() if n not in seen]

    def on_run(self, run: RunInfo, _k: str) -> None:
        with self.lock:
            self.run = run

    def on_truth(self, t: Truth, _k: str) -> None:
        with self.lock:
            self.truth.append(t)

    def on_nav(self, sol: NavSolution, _k: str) -> None:
        # Only kept: the error is worked out once per table (``errors``), not for each of the
        # ~350 solutions a second at 400 Hz (a nearest-truth search over 400 samples each was
        # several % of a core in the supervisor).
        with self.lock:
            self.nav_seen[sol.estimator] = time.monotonic()
            self.nav_last[sol.estimator] = sol

    def _update_errors(self) -> None:
        """Each estimator's latest horizontal error against the truth nearest in time (lock held)."""
        if not self.truth:
            return
        for name, sol in self.nav_last.items():
            # nearest truth sample in time (truth is 100 Hz, solutions are stamped on the IMU grid)
            best = min(self.truth, key=lambda t: abs(t.stamp_ns - sol.stamp_ns))
            if abs(best.stamp_ns - sol.stamp_ns) > self.TRUTH_MATCH_NS:
                continue
            d = np.subtract(sol.pos_ned_m, best.pos_ned_m)
            self.errors_m[name] = float(np.hypot(d[0], d[1]))

    def table(
        self,
        elapsed_s: float,
        alive: dict[str, bool] | None = None,
        *,
        title: str = "hil up",
        now: float | None = None,
    ) -> str:
        """The live table: one row per service, then the current error of every estimator."""
        now = time.monotonic() if now is None else now
        with self.lock:
            self._update_errors()
            run = self.run
            head = f"{title}  t={elapsed_s:7.1f} s"
            if run is not None:
                head += f"  rig {run.rig}  scenario {run.scenario}  speed {run.speed:g}x"
            cols = f"{'in/s':>8}{'out/s':>8}{'rejected':>9}{'errors':>7}"
            lines = [head, f"  {'service':<14}{'state':<12}{cols}  last error"]
            names = list(SERVICES) + sorted(n for n in self.status if n not in SERVICES)
            names += [n for n in alive or {} if n not in names]  # a child with no status (the unit)
            for name in names:
                st = self.status.get(name)
                age = now - self.status_seen.get(name, -1e9)
                is_alive = alive.get(name, False) if alive is not None else age < self.STALE_S
                if st is None:
                    state = "(no status)" if alive is None or is_alive else "DEAD"
                    lines.append(f"  {name:<14}{state:<12}")
                    continue
                rin = sum(r.value for r in st.rates_hz if r.key.startswith("in."))
                rout = sum(r.value for r in st.rates_hz if r.key.startswith("out."))
                rej = sum(c.value for c in st.counters if c.key.startswith("rejected"))
                errs = sum(c.value for c in st.counters if "error" in c.key)
                if alive is not None and not is_alive:
                    state = "DEAD"
                elif alive is None and not is_alive:
                    state = f"stale {age:.0f}s" if age < 1e8 else "stale"
                else:
                    state = st.state
                lines.append(
                    f"  {name:<14}{state:<12}{rin:8.0f}{rout:8.0f}{rej:9d}{errs:7d}  {st.last_error[:60]}"
                )
            if self.errors_m:
                errs_txt = "  ".join(f"{k} {v:.1f}" for k, v in sorted(self.errors_m.items()))
                lines.append(f"  horizontal error vs truth [m]: {errs_txt}")
            elif self.nav_seen:
                lines.append(f"  estimators: {', '.join(sorted(self.nav_seen))} (no truth to compare with)")
            return "\n".join(lines)


class SolutionSampler:
    """The table's error line without a Python wake-up per message. The solutions and the truth
    land in Zenoh's own ring buffers (``RingChannel``: no thread of ours, no GIL; the oldest
    dropped when full); each :meth:`drain` (once per table drawn) takes the newest truth batches
    and each estimator's newest solution that truth reaches, decoding only those. A 400 Hz rig
    publishes ~360 of these a second (seven estimators at 50 Hz, ten truth batches): delivered to
    a callback one by one they cost ``hil up``'s supervisor ~1.6 % of a core on a 2-CPU VM, where a
    wake-up costs ~28 µs (docs/benchmarks.md, session 40)."""

    NAV_RING = 2048  # ~5.8 s of seven estimators at 50 Hz: a draw every 5 s still sees each one's newest
    NAV_KEEP = 16  # each estimator's newest solutions looked at (0.32 s at 50 Hz)
    TRUTH_RING = 64  # truth batches, ten a second: 6.4 s
    TRUTH_KEEP = 8  # the newest batches decoded (0.8 s at 100 Hz)

    def __init__(self, session: zenoh.Session, keys: Keys, view: LiveView, stats: Stats) -> None:
        self.view = view
        self.stats = stats
        self.decoded = 0  # samples decoded by drain(): a few per estimator and TRUTH_KEEP a draw
        self._nav = session.declare_subscriber(keys.nav("*"), zenoh.handlers.RingChannel(self.NAV_RING))
        self._truth = session.declare_subscriber(keys.truth(), zenoh.handlers.RingChannel(self.TRUTH_RING))

    def drain(self) -> None:
        """Hand the view the newest truth and, per estimator, its newest solution that the truth
        reaches: the world publishes its truth ten rows at a time, so the very newest solution
        is often ahead of every truth row (by 32 ms in the one reading taken at 400 Hz; up to a
        batch's 100 ms and the delivery) and could not be compared."""
        newest: dict[str, deque[zenoh.Sample]] = {}
        while (s := self._nav.try_recv()) is not None:
            key = str(s.key_expr)
            q = newest.get(key)
            if q is None:
                q = newest[key] = deque(maxlen=self.NAV_KEEP)
            q.append(s)
        truth: deque[zenoh.Sample] = deque(maxlen=self.TRUTH_KEEP)
        while (s := self._truth.try_recv()) is not None:
            truth.append(s)
        view = self.view
        for s in truth:
            deliver_sample(s, Truth, view.on_truth, self.stats)
        self.decoded += len(truth)
        with view.lock:
            reach = view.truth[-1].stamp_ns + view.TRUTH_MATCH_NS if view.truth else None
        got: list[NavSolution] = []

        def keep(m: NavSolution, _k: str) -> None:
            got.append(m)

        for q in newest.values():
            chosen: NavSolution | None = None
            for s in reversed(q):  # newest first
                got.clear()
                deliver_sample(s, NavSolution, keep, self.stats)
                self.decoded += 1
                if not got:  # refused (counted in stats)
                    continue
                chosen = chosen or got[-1]  # the newest, should the truth reach none
                if reach is None or got[-1].stamp_ns <= reach:
                    chosen = got[-1]
                    break
            if chosen is not None:
                view.on_nav(chosen, "")

    def undeclare(self) -> None:
        self._nav.undeclare()
        self._truth.undeclare()


class TableDrawer:
    """Redraws a multi-line table in place on a TTY; appends it (less often) otherwise."""

    def __init__(self, out: IO[str] | None = None) -> None:
        self.out = out or sys.stdout
        self.tty = self.out.isatty()
        self.lines = 0

    def draw(self, text: str) -> None:
        if self.tty and self.lines:
            self.out.write(f"\x1b[{self.lines}F\x1b[J")
        self.out.write(text + "\n")
        self.out.flush()
        self.lines = text.count("\n") + 1


class Supervisor:
    """Starts the services, restarts dead ones (``--restart N`` per service), stops them in order.

    Every death, restart and the final give-up is published as ``hil.Event`` on
    ``hil/<rig>/event/supervisor`` (so the recording holds it) and printed. A restarted service is
    told so (option ``resume``): emulators and world rejoin at the current rig time, fusion
    re-aligns, the recorder writes ``<stem>.part<N>.mcap``.
    """

    def __init__(self, opts: UpOptions) -> None:
        self.opts = opts
        self.children: dict[str, Child] = {}
        self.stop = threading.Event()
        # a stop asked for by a signal (Ctrl-C, SIGTERM): its name, and the rig time it came at
        # (None before time zero), for the summary's line on a run cut short
        self.stopped_by: str | None = None
        self.stopped_at_s: float | None = None
        self.failures: list[str] = []
        self.restart_log: list[str] = []  # one line per restart, for the summary
        self.record_parts: list[Path] = []  # extra files written by restarted recorders
        self._event_pub: Publisher[Event] | None = None
        self._kills: list[tuple[int, str, str]] = []  # (rig ns, service, origin): kill_service faults
        self._kill_lock = threading.Lock()
        self.view = LiveView()
        self._sampler: SolutionSampler | None = None  # the table's solutions and truth (--quiet: none)
        self.usage: dict[str, Usage] = {}  # per service, since time zero, sampled just before the stop
        self.spawned_at: dict[str, float] = {}  # per service, monotonic time of its (last) start
        self.ready_cpu_s: dict[str, float] = {}  # per service, its process's CPU when first seen ready
        self.cpu_window_s = 0.0  # wall time those CPU seconds were spent in
        self._base: dict[str, Usage] = {}  # per live process, its usage at time zero (empty: before)
        self._cpu_base_t = time.monotonic()
        self.viewer: Child | None = None  # ``hil foxglove`` for ``--foxglove``: serves, never fails the run
        # per run (or HIL_RIG_KEY's): the rig's processes' Zenoh ids derive from it
        self.rig_key = rig_key_from_env() or new_rig_key()
        self._self_base = _own_usage()
        self._dead: dict[str, Usage] = {}  # the earlier lives of restarted services
        self._restarting: dict[str, tuple[float, int]] = {}  # name -> (when it died, new pid)
        self.downtime_s: dict[str, float] = {}  # per restarted service: dead until ready again
        self._degraded_seen: set[str] = set()
        env_cfg = BusConfig.from_env()
        self.access: RigAccess | None = None  # the embedded hub's endpoint and per-run secret
        if env_cfg.mode == "client" or os.environ.get("HIL_ZENOH_CONNECT"):
            self.hub_cfg = env_cfg
            self.child_bus = env_cfg
        else:
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            self.access = RigAccess.new(opts.rig, endpoint, authenticated=not opts.open_bus)
            self.hub_cfg = self.access.hub_config()
            self.child_bus = self.access.child_config()
        # the IMU's CAN bus, where the kernel has no such channel and the rig is on one machine:
        # Unix sockets in a directory of the rig's own (hil.can.local_bus), not through the hub
        from hil.can.bus import channel_exists

        self.can_dir: Path | None = None
        iface = (opts.interface or "auto").strip().lower()
        if self.access is not None and (
            iface == "hillocal" or (iface == "auto" and not channel_exists(opts.channel))
        ):
            self.can_dir = self.access.can_dir

    def endpoint_line(self) -> str:
        """What ``hil up`` prints about its bus: where it is and how a viewer gets in."""
        a = self.access
        if a is None:
            where = ", ".join(self.child_bus.connect) or "the configured network"
            return f"bus: joins {where} (HIL_ZENOH_* from the environment)"
        how = "authenticated per run" if a.authenticated else "OPEN: any local process may join (--open-bus)"
        return (
            f"bus: embedded hub {a.endpoint}, {how}; `hil monitor --rig {a.rig}` attaches "
            f"(endpoint file {a.name_path}, removed at exit)"
        )

    def service_names(self) -> list[str]:
        names = list(SERVICES)
        if self.opts.dut_emulator == "truth":
            names.insert(names.index("world"), "dut_emulator")
        elif self.opts.dut_emulator == "unit":
            names.insert(names.index("world"), DUT_UNIT)
        if self.opts.gnss_wire:  # the line's reader starts before the receiver
            names.insert(names.index("gnss_emulator"), "gnss_bridge")
        return names

    def bridge_line(self) -> str:
        """Where the rig's own GNSS bridge reads the receiver's line: a pty linked in the logs."""
        return str((self.opts.log_dir or Path("recordings/logs")) / "gnss_bridge.tty")

    def dut_line(self) -> str:
        """Where the unit (``--dut-emulator``) reads the receiver: a pty of its own, as a real
        unit has its own UART (two readers of one tty would split its bytes)."""
        return str((self.opts.log_dir or Path("recordings/logs")) / "dut_gnss.tty")

    def dut_command(self) -> list[str]:
        """The unit's program on the run's wires: the IMU's CAN bus (channel and interface: the
        rig's hillocal directory or hilzenoh network, which the environment every child gets
        configures) and its GNSS line."""
        from hil.can.bus import LOCAL_DIR_ENV, resolve_interface
        from hil.can.codec import default_dbc_path

        o = self.opts
        if not o.dut_mapping:
            raise ValueError("--dut-emulator needs --dut MAPPING.toml")
        cmd = [sys.executable, str(dut_program(o.dut_mapping))]
        can_env = {} if self.can_dir is None else {LOCAL_DIR_ENV: str(self.can_dir)}
        cmd += ["--can-interface", resolve_interface(o.channel, o.interface, can_env), "--channel", o.channel]
        cmd += ["--fd"] if o.fd else []
        cmd += ["--gnss", self.dut_line(), "--gnss-baud", str(o.gnss_baud)]
        return [*cmd, "--imu-dbc", str(default_dbc_path()), "--stop-with-pid", str(os.getpid())]

    def options_for(self, name: str, restarts: int = 0) -> dict[str, Any]:
        """The service's typed options from this run's (``hil.runtime.options.fill_options``)."""
        o = self.opts
        derived: dict[str, Any] = {}
        if name == "world":  # the unit publishes no status: the run does not wait for it
            derived["wait_for"] = [n for n in self.service_names() if n not in ("world", DUT_UNIT)]
            run = self.view.run
            if restarts and run is not None:
                # the same run again: time zero and scenario as announced, not a new run
                derived["resume_run"] = {f: getattr(run, f) for f in run.__struct_fields__}
        elif name == "recorder":
            path = o.record if not restarts or o.record is None else restart_part_path(o.record, restarts)
            if restarts and o.record is not None:  # the files of its earlier lives, oldest first
                derived["continues"] = [str(o.record)] + [
                    str(restart_part_path(o.record, k)) for k in range(1, restarts)
                ]
            derived.update(
                path=str(path),
                zenoh_advanced=o.zenoh_miss_detection,
                include=list(o.record_include),
                exclude=list(o.record_exclude),
            )
        elif name in ("gnss_emulator", "gnss_bridge") and o.gnss_wire:
            derived.update(protocol=o.gnss_protocol, baud=o.gnss_baud, messages=o.gnss_messages)
            if name == "gnss_emulator":
                links = [*([o.gnss_serial] if o.gnss_serial else []), self.bridge_line()]
                links += [self.dut_line()] if o.dut_emulator == "unit" else []
                derived.update(serial_links=links, tcp_listen=o.gnss_tcp)
            else:
                derived["serial_path"] = self.bridge_line()
        if restarts:
            derived["resume"] = restarts
        return fill_options(name, o, derived)

    def check_options(self) -> None:
        """Every service's options decoded now: a bad one is refused before any process starts
        (``hil.nodes.base.OptionsError``, naming the service and the field)."""
        for name in self.service_names():
            if name == DUT_UNIT:
                self.dut_command()
            else:
                self.options_for(name)

    def emit(self, kind: str, source: str, detail: str) -> None:
        """An ``hil.Event`` from the supervisor (recorded like any other rig traffic)."""
        pub = self._event_pub
        if pub is None:
            return
        run = self.view.run
        stamp = RigClock(run.start_epoch_ns, run.speed).now_ns() if run is not None else 0
        try:
            pub.put(
                Event(seq=pub.next_seq(), stamp_ns=max(stamp, 0), kind=kind, source=source, detail=detail)
            )
        except Exception as err:  # the hub closing must not hide the failure itself
            print(f"hil up: could not publish event {kind}: {err}", file=sys.stderr, flush=True)

    def _schedule_scenario_kills(self) -> None:
        """Timed ``kill_service`` events of the scenario (hil/faults.py), executed at their rig time."""
        from hil.nav.scenario import ScenarioError, load_scenario

        try:
            events = load_scenario(self.opts.scenario).events
        except ScenarioError:
            return  # world reports the scenario error itself
        for ev in events:
            if ev.kind == "kill_service":
                self._kills.append((round(ev.t_start_s * 1e9), str(ev.params["service"]), "scenario"))

    def _on_fault(self, cmd: FaultCommand, _key: str) -> None:
        """``hil fault kill_service --target S``: SIGKILL that service's process now."""
        if cmd.kind != "kill_service":
            return
        with self._kill_lock:
            self._kills.append((0, cmd.target, "command"))

    def _do_kills(self) -> None:
        run = self.view.run
        if not self._kills or run is None:
            return
        now = RigClock(run.start_epoch_ns, run.speed).now_ns()
        with self._kill_lock:
            due = [k for k in self._kills if k[0] <= now]
            self._kills = [k for k in self._kills if k[0] > now]
        for t_ns, name, origin in due:
            child = self.children.get(name)
            detail = json.dumps({"kind": "kill_service", "origin": origin, "target": name, "t_s": now / 1e9})
            if child is None or child.proc.poll() is not None:
                self.emit("fault_rejected", "supervisor", detail + f" (no running service {name!r})")
                continue
            self.emit("fault_start", "supervisor", detail)
            print(f"hil up: fault kill_service: SIGKILL {name} (pid {child.proc.pid}, {origin})", flush=True)
            child.proc.kill()
            _ = t_ns

    def _child_env(self) -> dict[str, str]:
        env = dict(os.environ)
        use_rig_runtime(env)
        env.update(self.child_bus.to_env())
        env["HIL_RIG"] = self.opts.rig
        env["HIL_SUPERVISOR_PID"] = str(os.getpid())  # children stop themselves if we vanish
        # the rig's identity on the bus (hil.bus.identity): this child's Zenoh id, and the run's
        # key that lets the recorder recognise every rig process's id
        env[RIG_KEY_ENV] = self.rig_key
        env[ZENOH_ID_ENV] = rig_zid(self.rig_key)
        if not self.opts.zenoh_miss_detection:
            env[MISS_DETECTION_ENV] = "0"  # plain Zenoh publishers in every service
        if self.can_dir is not None:  # their CAN bus (hil.can.bus.resolve_interface: hillocal)
            from hil.can.bus import LOCAL_DIR_ENV

            env[LOCAL_DIR_ENV] = str(self.can_dir)
        if self.opts.rig_cpus:  # each service takes it first thing (``hil service``)
            env[RIG_CPUS_ENV] = ",".join(str(c) for c in self.opts.rig_cpus)
        env.setdefault("PYTHONUNBUFFERED", "1")
        return env

    def spawn_viewer(self) -> Child:
        """``hil foxglove`` on the rig's bus, attached as a remote one would be (read-only)."""
        assert self.opts.foxglove is not None
        log_dir = self.opts.log_dir or Path("recordings/logs")
        log_dir.mkdir(parents=True, exist_ok=True)
        log_path = log_dir / "foxglove.log"
        fh = open(log_path, "ab")  # noqa: SIM115 - owned by the Child
        cmd = [sys.executable, "-m", "hil.cli", "foxglove", "--rig", self.opts.rig]
        cmd += ["--listen", self.opts.foxglove]
        proc = subprocess.Popen(
            cmd, stdout=fh, stderr=subprocess.STDOUT, env=self._child_env(), start_new_session=True
        )
        self.viewer = Child("foxglove", proc, log_path, fh)
        return self.viewer

    def _check_viewer(self) -> None:
        v = self.viewer
        if v is None or v.stopping or v.proc.poll() is None:
            return
        v.stopping = True  # said once; the rig runs on (the recording is the product)
        print(
            f"hil up: the Foxglove server exited (code {v.proc.returncode}); the rig runs on. "
            f"See {v.log_path}:\n{_tail(v.log_path)}",
            file=sys.stderr,
            flush=True,
        )

    def _stop_viewer(self) -> None:
        v = self.viewer
        if v is None:
            return
        if v.proc.poll() is None:
            v.proc.send_signal(signal.SIGTERM)
            try:
                v.proc.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                v.proc.kill()
                v.proc.wait()
        v.log_fh.close()

    def spawn(self, name: str, restarts: int = 0) -> Child:
        log_dir = self.opts.log_dir or Path("recordings/logs")
        log_dir.mkdir(parents=True, exist_ok=True)
        log_path = log_dir / f"{name}.log"
        fh = open(log_path, "ab")  # noqa: SIM115 - owned by the Child
        env = self._child_env()
        if name == DUT_UNIT:
            cmd = self.dut_command()
        else:
            options = json.dumps(self.options_for(name, restarts))
            cmd = [sys.executable, "-m", "hil.cli", "service", name, "--rig", self.opts.rig]
            cmd += ["--options", options]
        if restarts:
            fh.write(f"\n--- hil up: restart {restarts} of {name} ---\n".encode())
            fh.flush()
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        child = Child(name, proc, log_path, fh, restarts=restarts)
        self.spawned_at[name] = time.monotonic()
        with self.view.lock:
            self.view.ready_at.pop(name, None)  # a restart becomes ready again
            self.ready_cpu_s.pop(name, None)
        self.children[name] = child
        return child

    def run(self) -> int:
        from hil.can.local_bus import remove_can_dir

        o = self.opts
        hub_cfg = dataclasses.replace(self.hub_cfg, extra={**self.hub_cfg.extra, "id": rig_zid(self.rig_key)})
        if self.access is not None:
            self.access.write()  # before the hub opens: it reads the dictionary from there
            remove_stale_run_files(self.access.dir)  # a killed run's own files (its secret) do not pile up
        if self.can_dir is not None:  # ``hil up`` says where (hil.cli._describe_can)
            _remove_stale_can_dirs(self.can_dir.parent)
            remove_can_dir(self.can_dir)  # a killed run's with this pid
            self.can_dir.mkdir(mode=0o700)
        # --rig-cpus: the hub's threads too (they route every message), restored at the end
        mask, note = pin_process(o.rig_cpus)
        if note:
            print(f"hil up: {note}", file=sys.stderr)
        try:
            session = open_session(hub_cfg)
        except BaseException:
            self._remove_run_files(mask)
            raise
        keys = Keys(o.rig)
        stats = Stats()
        subs = [
            Subscriber(session, keys.status("*"), ServiceStatus, self.view.on_status, stats),
            Subscriber(session, keys.run(), RunInfo, self.view.on_run, stats),
        ]
        # the table's error line (--quiet draws no table): taken from rings at each draw
        self._sampler = SolutionSampler(session, keys, self.view, stats) if o.live else None
        self._event_pub = Publisher(
            session, keys.event("supervisor"), Event, stats, miss_detection=o.zenoh_miss_detection
        )
        subs.append(Subscriber(session, keys.control("fault"), FaultCommand, self._on_fault, stats))
        self._schedule_scenario_kills()
        prev = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        self._stop_setter = EventSetter(self.stop)  # hil.runtime.signals: never stop.set() there
        for s in prev:
            signal.signal(s, self._on_stop_signal)
        t_start = self._t_start = time.monotonic()
        try:
            if o.foxglove:
                self.spawn_viewer()  # first: it sees the run from its first message
            for name in self.service_names():
                self.spawn(name)
            self._wait(t_start)
        finally:
            self._stop_viewer()
            self._stop_all()
            self._final_accounting()
            for s, h in prev.items():
                signal.signal(s, h)
            self._stop_setter.close()
            for sub in subs:
                sub.undeclare()
            if self._sampler is not None:
                self._sampler.undeclare()
            self._event_pub = None
            session.close()
            self._remove_run_files(mask)
        return 1 if self.failures else 0

    def _on_stop_signal(self, signum: int, _frame: object) -> None:
        if self.stopped_by is None:
            self.stopped_by = signal.Signals(signum).name
            run = self.view.run
            if run is not None:
                self.stopped_at_s = RigClock(run.start_epoch_ns, run.speed).now_ns() / 1e9
        self._stop_setter()

    def stop_line(self) -> str | None:
        """A run a signal cut short of its ``--duration``: when, so the summary says it (the
        exit code stays 0: a stop asked for is a clean one)."""
        d = self.opts.duration_s
        if self.stopped_by is None or d is None:
            return None
        if self.stopped_at_s is None:
            return f"stopped by {self.stopped_by} before time zero: nothing of the {d:g} s asked was run"
        if self.stopped_at_s >= d:
            return None
        return f"stopped by {self.stopped_by} at {self.stopped_at_s:.1f} s of the {d:g} s asked"

    def _remove_run_files(self, mask: set[int] | None) -> None:
        """What ``run`` made for this run, undone: the CPU mask, the endpoint file, the CAN directory."""
        from hil.can.local_bus import remove_can_dir

        unpin_process(mask)
        if self.access is not None:
            self.access.remove()
        if self.can_dir is not None:
            remove_can_dir(self.can_dir)

    def _wait(self, t_start: float) -> None:
        o = self.opts
        drawer = TableDrawer()
        tty = drawer.tty
        last_print = 0.0
        while not self.stop.wait(0.2):
            self._do_kills()
            self._check_viewer()
            if self._check_deaths():
                return
            self._check_degraded()
            self._check_restarts()
            self._note_ready_cpu()
            run = self.view.run
            if run is not None and not self._base:
                self._cpu_base_t = time.monotonic()
                self._self_base = _own_usage()
                for name, c in self.children.items():
                    self._base[name] = proc_usage(c.proc.pid) or Usage()
            if run is not None and o.duration_s is not None:
                clock = RigClock(run.start_epoch_ns, run.speed)
                if clock.now_ns() >= int((o.duration_s + 0.3) * 1e9):
                    return
            if run is None and time.monotonic() - t_start > 120:
                self.failures.append(
                    "the run never started: no RunInfo from world within 120 s (see the logs)"
                )
                return
            now = time.monotonic()
            if o.live and now - last_print >= (1.0 if tty else 5.0):
                last_print = now
                alive = {n: c.proc.poll() is None for n, c in self.children.items()}
                if self._sampler is not None:
                    self._sampler.drain()
                drawer.draw(self.view.table(now - t_start, alive))

    def _check_deaths(self) -> bool:
        """Restart what died (``--restart N``); True when a death ends the run."""
        o = self.opts
        for name, child in list(self.children.items()):
            rc = self._reap(child)
            if rc is None or child.stopping:
                continue
            tail = _tail(child.log_path)
            how = f"killed by signal {-rc}" if rc < 0 else f"exit code {rc}"
            if child.restarts < o.restart:
                n = child.restarts + 1
                child.log_fh.close()
                self._retire_cpu(name, child)
                new = self.spawn(name, n)
                self._restarting[name] = (time.monotonic(), new.proc.pid)
                line = f"{name} died ({how}); restarted ({n}/{o.restart}) as pid {new.proc.pid}"
                if name == "recorder" and o.record is not None:
                    part = restart_part_path(o.record, n)
                    self.record_parts.append(part)
                    line += f", recording continues in {part}"
                self.restart_log.append(line)
                print(f"hil up: {line}", flush=True)
                self.emit("service_restarted", name, line)
                continue
            reason = (
                f"{name} died ({how}) after {child.restarts} restart(s) of {o.restart} allowed"
                if o.restart
                else f"{name} died ({how}) during the run (--restart 0)"
            )
            self.failures.append(f"{reason}; last log lines:\n{tail}")
            print(f"hil up: {reason}; stopping the rig", flush=True)
            self.emit("run_failed", name, reason)
            return True
        return False

    def _reap(self, child: Child) -> int | None:
        """The child's exit code once it has ended (None while it runs), reaped with its rusage:
        a dead process's CPU is gone from /proc, and its successor's count starts again at 0 --
        subtracting the old base from it once showed "fusion -0.93 s" after a restart."""
        if child.proc.returncode is not None:
            return child.proc.returncode
        try:
            pid, status, usage = os.wait4(child.proc.pid, os.WNOHANG)
        except ChildProcessError:  # reaped elsewhere (Popen.wait): nothing more to learn
            return child.proc.poll()
        if pid == 0:
            return None
        child.proc.returncode = os.waitstatus_to_exitcode(status)
        child.final = Usage(usage.ru_utime + usage.ru_stime, usage.ru_nvcsw)
        return child.proc.returncode

    def _retire_cpu(self, name: str, child: Child) -> None:
        """Add a dead life's usage (since time zero, or since its own start) to the service's total."""
        spent = (child.final or Usage()).since(self._base.get(name, Usage()))
        self._dead[name] = self._dead.get(name, Usage()) + spent
        if self._base:
            self._base[name] = Usage()  # the next life is counted from its own start

    def _check_degraded(self) -> None:
        """Say at once, on the console, when a service reports itself degraded (a recorder that
        cannot write): its log may sit on the very disk that is full."""
        for name, reason in self.view.degraded_since(self._degraded_seen):
            self._degraded_seen.add(name)
            line = f"{name} is DEGRADED: {reason}"
            print(f"hil up: {line}", file=sys.stderr, flush=True)
            self.emit("service_degraded", name, line)

    def _check_restarts(self) -> None:
        """A restarted service is down until its new process reports ``running``; past the
        deadline it counts as a failure of the run (it stayed "starting" once, silently)."""
        now = time.monotonic()
        for name, (t_died, pid) in list(self._restarting.items()):
            st = self.view.status.get(name)
            if st is not None and st.pid == pid and st.state in ("running", "degraded"):
                down = now - t_died
                self.downtime_s[name] = self.downtime_s.get(name, 0.0) + down
                self.restart_log.append(f"{name} ready again (pid {pid}) after {down:.1f} s down")
                del self._restarting[name]
            elif pid != -1 and now - t_died > self.opts.restart_ready_s:
                state = st.state if st is not None and st.pid == pid else "no status"
                reason = (
                    f"{name} was restarted (pid {pid}) but is not ready after "
                    f"{self.opts.restart_ready_s:g} s (state: {state}): down for the rest of the run"
                )
                self.failures.append(reason)
                print(f"hil up: {reason}", file=sys.stderr, flush=True)
                self.emit("run_failed", name, reason)
                self._restarting[name] = (t_died, -1)  # reported once; still down

    def _final_accounting(self) -> None:
        """Downtime of services that never came back, and every degradation, as failures."""
        now = time.monotonic()
        for name, (t_died, pid) in self._restarting.items():
            self.downtime_s[name] = self.downtime_s.get(name, 0.0) + (now - t_died)
            if pid != -1:
                self.failures.append(f"{name} was restarted but never became ready before the stop")
        self._check_degraded()
        silent = self._silent_imu()
        if silent:
            self.failures.append(silent)
        for name, reason in self.view.degraded_since(set()):
            if not any(f.startswith(f"{name} ") for f in self.failures):
                self.failures.append(f"{name} degraded: {reason}")

    def _silent_imu(self, min_run_s: float = 3.0) -> str | None:
        """The IMU is the rig's clock: a run whose CAN bridge decoded not one sample produced no
        navigation at all, yet every service stayed up -- so say so instead of exiting 0."""
        if "can_bridge" not in self.children or not self._base:
            return None  # no bridge in this rig, or the run never started
        ran_s = time.monotonic() - self._cpu_base_t
        st = self.view.status.get("can_bridge")
        if ran_s < min_run_s or st is None:
            return None
        counts = st.counter_map()
        if counts.get("can.samples", 0) > 0:
            return None
        return (
            f"can_bridge decoded no IMU sample in {ran_s:.0f} s of run (CAN frames received: "
            f"{counts.get('can.frames', 0)}): the IMU's frames never reached it; see the logs of "
            "imu_emulator and can_bridge"
        )

    def _sample_cpu(self) -> None:
        """CPU seconds each service spent since time zero (start-up imports excluded; a restarted
        service's earlier lives included), and the supervisor's own."""
        self.cpu_window_s = time.monotonic() - self._cpu_base_t
        for name, c in self.children.items():
            now = proc_usage(c.proc.pid) if c.proc.returncode is None else c.final
            live = now.since(self._base.get(name, Usage())) if now is not None else Usage()
            self.usage[name] = self._dead.get(name, Usage()) + live
        self.usage["supervisor"] = _own_usage().since(self._self_base)

    @property
    def cpu_s(self) -> dict[str, float]:
        """CPU seconds per service (and the supervisor) since time zero: :attr:`usage`'s."""
        return {name: u.cpu_s for name, u in self.usage.items()}

    def ready_s(self) -> dict[str, float]:
        """Seconds from each service's process start to its first ready status (the world waits
        for these before it picks time zero)."""
        with self.view.lock:
            ready = dict(self.view.ready_at)
        return {n: ready[n] - t for n, t in self.spawned_at.items() if n in ready}

    def _note_ready_cpu(self) -> None:
        """Each service's CPU seconds when it is first seen ready: what its start-up cost,
        whatever the machine's load (sampled within this loop's 0.2 s, while it waits for the
        run; its own process, not a CAN sender it started)."""
        with self.view.lock:
            ready = [n for n in self.view.ready_at if n not in self.ready_cpu_s]
        for name in ready:
            child = self.children.get(name)
            if child is None or child.proc.returncode is not None:
                continue
            cpu = proc_cpu_seconds(child.proc.pid, tree=False)
            if cpu is not None:
                self.ready_cpu_s[name] = cpu

    def ready_cpu_line(self) -> str:
        r = self.ready_cpu_s
        if not r:
            return ""
        parts = ", ".join(f"{n} {s:.2f}" for n, s in sorted(r.items(), key=lambda kv: -kv[1]))
        return f"CPU to ready (s): {parts}"

    def ready_line(self) -> str:
        r = self.ready_s()
        if not r:
            return ""
        parts = ", ".join(f"{n} {s:.2f}" for n, s in sorted(r.items(), key=lambda kv: -kv[1]))
        return f"ready after start (s): {parts}"

    def pacing_line(self, min_late_share: float = 0.01) -> str:
        """How many IMU samples the frame sender handed over more than 200 µs late (its last
        status); when more than ``min_late_share`` were, what would help that was not asked for:
        the placement that gives it a CPU of its own (a machine with CPUs to spare) and real-time
        priority ("" when nothing was counted)."""
        emu, bridge = self.view.status.get("imu_emulator"), self.view.status.get("can_bridge")
        if emu is None or bridge is None:
            return ""
        c = emu.counter_map()
        late, worst_us = c.get("tx_late_samples"), c.get("tx_late_max_us", 0)
        n = bridge.counter_map().get("can.samples", 0)
        if late is None or n <= 0:
            return ""
        line = f"IMU frames: {late} of {n} samples handed to the bus more than 200 µs late"
        line += f" (worst {worst_us / 1e3:.1f} ms)"
        o = self.opts
        if late <= min_late_share * n or o.rt_priority:
            return line
        helps = []
        if (os.cpu_count() or 1) >= 2 and not o.rig_cpus and not o.cpu_affinity:
            helps.append("--cpu-affinity 1 --rig-cpus 0 gives the sender a CPU of its own")
        # measured on a 2-CPU VM at 400 Hz: p99 88-141 µs at SCHED_FIFO 50, 320-1082 µs without
        helps.append(
            "--rt-priority 50 runs the sender at real-time priority where permitted (root or CAP_SYS_NICE)"
        )
        return f"{line}; {', or '.join(helps)} (docs/timing.md)"

    def cpu_table(self) -> str:
        if not self.usage or self.cpu_window_s <= 0:
            return ""
        w = self.cpu_window_s

        def row(name: str, u: Usage) -> str:
            return (
                f"  {name:<14}{u.cpu_s:8.2f} s  {100 * u.cpu_s / w:6.1f} %  {u.wakeups / w:7.0f} wake-ups/s"
            )

        rows = [f"CPU over {w:.1f} s of wall time (share of one core; wake-ups: its threads' a second):"]
        rows += [row(name, u) for name, u in sorted(self.usage.items(), key=lambda kv: -kv[1].cpu_s)]
        rows.append(row("all", sum(self.usage.values(), Usage())))
        return "\n".join(rows)

    def _stop_all(self) -> None:
        if self.children and not self.usage:
            self._sample_cpu()
        for stage in STOP_STAGES:
            procs = [self.children[n] for n in stage if n in self.children]
            for c in procs:
                c.stopping = True
                if c.proc.poll() is None:
                    c.proc.send_signal(signal.SIGTERM)
                    # a stopped process (SIGSTOP, a debugger's) never sees SIGTERM until it runs:
                    # continue it, as systemd does, so it ends cleanly instead of at the deadline
                    c.proc.send_signal(signal.SIGCONT)
            # generous: a service that is behind on a loaded machine (the IMU emulator catching
            # up, at load 35 on 2 cores) needs more than 10 s to end; an idle one ends in < 1 s
            deadline = time.monotonic() + 30.0
            for c in procs:
                try:
                    c.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    c.proc.kill()
                    c.proc.wait()
                    self.failures.append(f"{c.name} did not stop within its deadline and was killed")
                rc = c.proc.returncode
                if (
                    rc not in (0, -signal.SIGTERM)
                    and not any(f.startswith(c.name) for f in self.failures)
                    and c.name not in self.view.degraded  # its own reason says more (_final_accounting)
                ):
                    self.failures.append(
                        f"{c.name} exited with code {rc} at stop; see {c.log_path}:\n{_tail(c.log_path)}"
                    )
                c.log_fh.close()


def _own_usage() -> Usage:
    """This process's CPU and voluntary context switches (every thread; children not included)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return Usage(r.ru_utime + r.ru_stime, r.ru_nvcsw)


def _tail(path: Path, n: int = 8) -> str:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    return "\n".join("    " + ln for ln in lines[-n:])
