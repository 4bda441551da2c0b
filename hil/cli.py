"""``hil``: the rig's command line. Argument parsing lives here; the work lives in the library.

Errors a user can fix (a bad path, an unknown scenario, a malformed option) end with one line
saying what and where, and exit code 2 -- never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

from hil import __version__
from hil.runtime import heap
from hil.runtime.argtypes import (
    OneLineParser,
    bounded_float,
    bounded_int,
    duration_s,
    positive_float,
    restart_count,
    seconds,
    speed,
)
from hil.runtime.errors import WorkerError

EXIT_USAGE = 2
GNSS_BAUD = 115200  # the receiver line's baud rate without --gnss-baud
ROUTER_LISTEN = "tcp/127.0.0.1:7447"  # hil router with neither --listen nor --config: this host only


class UserError(Exception):
    """An error the user can fix; printed as one line."""


def _message(err: BaseException) -> str:
    """An exception's own message: a KeyError's ``str()`` is the repr of its argument (quoted)."""
    if isinstance(err, KeyError) and len(err.args) == 1 and isinstance(err.args[0], str):
        return err.args[0]
    return str(err)


def _estimators(text: str | None) -> list[str]:
    """``--estimators``: not given, the defaults (an empty list to the fusion); given, its names."""
    from hil.estimators.names import estimator_names

    if text is None:
        return []
    try:
        return estimator_names(text)
    except ValueError as err:
        raise UserError(str(err)) from None


_FUSION_FLAGS = (
    ("unknown estimator", "--estimators: "),
    ("estimators: ", "--"),
    ("feedback", "--"),
    ("ekf_calibration", "--"),
)


def _check_fusion_choices(a: argparse.Namespace) -> None:
    """``--estimators``, ``--feedback`` and ``--ekf-calibration`` together, now, in one line each
    (the fusion's options say it later, as a ValueError), and no feedback or calibration for an
    estimator the run does not run (the fusion would leave it out: a choice with no effect)."""
    from hil.nodes.fusion import FusionOptions

    try:
        opts = FusionOptions(
            estimators=_estimators(a.estimators), feedback=a.feedback, ekf_calibration=a.ekf_calibration
        )
        problem = opts.unused_choice()
    except ValueError as err:
        problem = str(err)
    if problem:
        flag = next((f for start, f in _FUSION_FLAGS if problem.startswith(start)), "")
        raise UserError((flag + problem).replace("--ekf_calibration", "--ekf-calibration"))


def _default_record_path(scenario: str) -> Path:
    stem = Path(scenario).stem
    return Path("recordings") / f"{stem}-{datetime.now().strftime('%Y%m%d-%H%M%S')}.mcap"


def _keep_earlier_recording(record: Path) -> None:
    """``hil up`` at a path that holds a recording: moved aside now, with the parts it continues
    in and its services' logs (``<stem>.logs``, which the new run's would otherwise be appended
    to), before any service starts (``hil.record.mcapio.keep_aside``: a live session cannot be
    made again; a recorder started alone, as docker compose runs it, does the same itself). Part
    names left by an older recording stay, and are said: readers leave them out."""
    from hil.record.mcapio import keep_aside, session_files, stale_parts_note

    logs = record.with_suffix(".logs")
    try:
        kept = keep_aside(record)
        kept_logs = kept.with_suffix(".logs") if kept is not None else None
        if kept_logs is not None and logs.is_dir() and not kept_logs.exists():
            logs.rename(kept_logs)
    except OSError as err:
        raise UserError(
            f"--record {record}: it holds an earlier recording that cannot be moved aside "
            f"({err.strerror}); give another --record"
        ) from None
    if kept is not None:
        with_logs = f" (its logs as {kept_logs.name})" if kept_logs is not None and kept_logs.is_dir() else ""
        more = len(session_files(kept)) - 1
        with_parts = f" with its {more} later file(s)" if more else ""
        said = f"kept as {kept}{with_parts}{with_logs}, not written over"
        print(f"hil up: {record} held an earlier recording: {said}", file=sys.stderr)
    note = stale_parts_note(record)
    if note:
        print(f"hil up: warning: {note}", file=sys.stderr)


def _add_fusion_args(p: argparse.ArgumentParser) -> None:
    """The fusion's horizon and output predictor (docs/concepts.md, Fusion)."""
    p.add_argument(
        "--fusion-lag",
        type=bounded_float(0.0, 60.0, unit="s"),
        default=None,
        metavar="S",
        help="the fusion horizon's lag behind the newest IMU sample, the bound on a source's "
        "latency (default: the fusion's, 0.5)",
    )
    p.add_argument(
        "--no-output-predictor",
        action="store_true",
        help="publish the fusion horizon's state, lag late (the fusion before the output predictor)",
    )


def _add_run_args(p: argparse.ArgumentParser, default_duration: float | None) -> None:
    p.add_argument("--scenario", default="straight_level", help="built-in name or path to a scenario TOML")
    p.add_argument("--duration", type=duration_s, default=default_duration, help="seconds of rig time")
    p.add_argument(
        "--record", type=Path, default=None, help="MCAP path (default: recordings/<scenario>-<time>.mcap)"
    )
    p.add_argument("--rig", default="bench", help="rig name: namespaces every key as hil/<rig>/...")
    p.add_argument(
        "--estimators",
        default=None,
        help="comma-separated estimator names, each once (default: the registry's; ins alone: the "
        "free INS alone)",
    )
    p.add_argument(
        "--feedback",
        default="auto",
        help="seed estimators in feedback form (the INS reset by their estimate): auto (by the IMU "
        "grade: consumer MEMS), none, or comma-separated names",
    )
    p.add_argument(
        "--ekf-calibration",
        default="auto",
        help="ekf15's sensor-calibration states: auto (by the IMU grade), none, gyro, gyro+accel",
    )
    p.add_argument(
        "--split-mb",
        type=positive_float,
        default=None,
        help="start a new recording part (<stem>_0001.mcap, ...) after this many MB",
    )
    p.add_argument(
        "--split-s",
        type=positive_float,
        default=None,
        help="start a new recording part after this many seconds (hil sim: of rig time)",
    )
    p.add_argument(
        "--imu-rate",
        type=bounded_int(100, 2000),
        default=None,
        help="IMU rate in Hz (overrides the scenario's; 100-2000)",
    )
    p.add_argument(
        "--record-include",
        action="append",
        default=[],
        metavar="KEYEXPR",
        help="record only keys matching this Zenoh key expression (repeat; relative to hil/<rig>/)",
    )
    p.add_argument(
        "--record-exclude", action="append", default=[], metavar="KEYEXPR", help="do not record these keys"
    )


def _check_record_filter(a: argparse.Namespace) -> None:
    from hil.record.keyfilter import KeyFilter, KeyFilterError

    try:
        KeyFilter(a.rig, a.record_include, a.record_exclude)
    except KeyFilterError as err:
        raise UserError(f"--record-include/--record-exclude: {err}") from None
    import re

    chunk = re.compile(r"^(\*\*|(\$\*|[A-Za-z0-9_.\-])+|\*)$")
    for flag, patterns in (("--record-include", a.record_include), ("--record-exclude", a.record_exclude)):
        for pattern in patterns:
            bad = [c for c in pattern.strip("/").split("/") if not chunk.match(c)]
            if bad:
                raise UserError(
                    f"{flag} {pattern!r}: {bad[0]!r} can match no key of the rig (its keys are names "
                    "of A-Z a-z 0-9 _ . - joined by /; the wildcards are * and **: a Zenoh key "
                    "expression, not a glob)"
                )


def _add_gnss_wire_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--gnss-protocol",
        default=None,
        help="the GNSS receiver on a serial line: nmea, ubx or nmea,ubx (default with --gnss-serial: nmea)",
    )
    p.add_argument(
        "--gnss-baud",
        type=bounded_int(1, 10_000_000),
        default=None,
        help=f"the receiver line's baud rate (8N1; default {GNSS_BAUD})",
    )
    p.add_argument(
        "--gnss-messages",
        default="",
        help="the receiver's message set, e.g. GGA,RMC,GSA,ZDA or NAV-PVT,TIM-TP (default: the protocol's)",
    )


def _gnss_wire(a: argparse.Namespace, live: bool) -> dict[str, object]:
    """The receiver-on-a-wire settings, checked here with one line each (hil.wire)."""
    on_a_wire = live and (a.gnss_serial or a.gnss_tcp or a.dut_emulator == "unit")
    wanted = a.gnss_protocol or ("nmea" if on_a_wire else "")
    protocols = [p for p in wanted.split(",") if p]
    messages = [m for m in a.gnss_messages.split(",") if m]
    baud = GNSS_BAUD if a.gnss_baud is None else a.gnss_baud
    if not protocols and (messages or a.gnss_baud is not None):
        given = "--gnss-messages" if messages else "--gnss-baud"
        raise UserError(
            f"{given} without --gnss-protocol: the receiver is on no wire, so it would be ignored; "
            "add --gnss-protocol nmea (or ubx, nmea,ubx)"
        )
    if protocols:
        from hil.nodes.gnss_emulator import check_wire

        try:
            check_wire(protocols, messages, "GN", baud)
        except (KeyError, ValueError) as err:
            raise UserError(f"--gnss-protocol/--gnss-messages/--gnss-baud: {_message(err)}") from None
    if live and a.gnss_serial:
        p = Path(a.gnss_serial)
        if p.exists() and not p.is_symlink():
            raise UserError(
                f"--gnss-serial {p}: exists and is not a link; give a new path (the rig makes the link)"
            )
        probe = p.parent / f".hil-link-probe-{os.getpid()}"
        try:  # a trial link, not os.access: root passes access checks on /proc and read-only mounts
            os.symlink(os.devnull, probe)
            probe.unlink()
        except OSError as err:
            raise UserError(
                f"--gnss-serial {p}: cannot make a link in {p.parent} ({err.strerror}); give a path in a "
                "writable directory"
            ) from None
    return {"gnss_protocol": protocols, "gnss_baud": baud, "gnss_messages": messages}


def _load_warnings(scenario: Any, a: argparse.Namespace, wire: dict[str, Any]) -> list[str]:
    """The IMU's CAN bus or the receiver's line asked to carry more than it can, said before the
    run (which still goes: the IMU's frames queue and the session stretches; the line's UART
    overruns and loses epochs). The loads are the models' own: ``ImuCanCodec.bus_load`` (the
    bit timing of ``hil.can.busload``) and ``hil.nodes.gnss_emulator.line_load``."""
    from hil.can.codec import CodecError, ImuCanCodec

    out: list[str] = []
    rate = a.imu_rate or scenario.imu.rate_hz
    # ``hil up --speed K``: the bus and the line keep their bit rates in wall time, where the rig
    # sends K times as much a second
    k = float(getattr(a, "speed", None) or 1.0)
    at_speed = f" at --speed {k:g}" if k != 1.0 else ""
    try:
        codec = ImuCanCodec.from_dbc(fd=a.fd)
    except CodecError:  # a bad HIL_DBC: the IMU's service says so itself
        codec = None
    load = k * codec.bus_load(rate) if codec is not None else 0.0
    if codec is not None and load > 1.0:
        idle = codec.bus_load(0.0)  # the sync frame a second
        top = int((1.0 / k - idle) / (codec.bus_load(1.0) - idle))
        mode = "CAN FD" if a.fd else f"classic CAN ({len(codec.part_layouts)} frames a sample)"
        fix = (
            f"--imu-rate {top} or lower"
            if a.fd
            else f"--fd (one frame a sample) or --imu-rate {top} or lower"
        )
        out.append(
            f"the IMU at {rate} Hz{at_speed} loads its {mode} bus to {load * 100:.1f} %: its frames will "
            f"queue and the session stretch past its duration; use {fix}"
        )
    protocols, messages, baud = wire["gnss_protocol"], wire["gnss_messages"], wire["gnss_baud"]
    if protocols:
        from hil.nodes.gnss_emulator import line_load

        fixes = scenario.gnss.rate_hz
        line = k * line_load(protocols, messages, baud, fixes)
        if line > 1.0:
            least = next((b for b in _BAUDS if k * line_load(protocols, messages, b, fixes) <= 1.0), None)
            fix = f"--gnss-baud {least} or more" if least else "a faster line"
            out.append(
                f"the GNSS line at {baud} baud is loaded to {line * 100:.1f} % by {'+'.join(protocols)} at "
                f"{fixes:g} fixes a second{at_speed}: epochs will overrun the receiver's UART and be lost; "
                f"use {fix}, or fewer --gnss-messages"
            )
    return out


def _warn_loads(prog: str, scenario: Any, a: argparse.Namespace, wire: dict[str, Any]) -> None:
    for line in _load_warnings(scenario, a, wire):
        print(f"{prog}: warning: {line}", file=sys.stderr)


def lag_warning(scenario: Any, lag_s: float | None) -> str | None:
    """Why the fusion will refuse the scenario's GNSS fixes as late, or None: its lag (``lag_s``,
    ``--fusion-lag``; None: the fusion's default) below the receiver's
    output latency (the scenario's ``gnss.latency_s``, plus its jitter). Said before the run,
    not refused: a run may be meant to test exactly that (its end then says FAILED)."""
    from hil.nodes.fusion import DEFAULT_LAG_S

    g = scenario.gnss
    lag, latency, worst = DEFAULT_LAG_S if lag_s is None else lag_s, g.latency_s, g.latency_s + g.jitter_s
    if lag >= worst:
        return None
    which = "its fixes" if lag < latency else "the fixes its jitter takes past it"
    said = f"--fusion-lag {lag:g} s" if lag_s is not None else f"the fusion's lag ({lag:g} s, its default)"
    fix = f"give --fusion-lag above {worst:g} s to fuse them"
    return (
        f"{said} is below the GNSS receiver's output latency in scenario {scenario.name!r} "
        f"(gnss.latency_s {latency:g} s + jitter_s {g.jitter_s:g} s): the fusion will refuse {which} "
        f"as late and its estimators go without GNSS; {fix}"
    )


def lag_run_warning(lag_s: float | None, duration_s: float | None) -> str | None:
    """Why nothing will be fused, or None: a ``--fusion-lag`` as long as the run or longer (the
    horizon never moves: every estimator publishes its initial state carried by the IMU)."""
    if lag_s is None or duration_s is None or lag_s < duration_s:
        return None
    return (
        f"--fusion-lag {lag_s:g} s is the whole run ({duration_s:g} s) or more: the fusion's horizon "
        "never moves, no input is fused, and every estimator publishes its initial state carried "
        "forward by the IMU; give a lag well under the run's length"
    )


def _warn_lag(prog: str, scenario: Any, lag_s: float | None, duration_s: float | None) -> None:
    for line in (lag_warning(scenario, lag_s), lag_run_warning(lag_s, duration_s)):
        if line:
            print(f"{prog}: warning: {line}", file=sys.stderr)


_WIRE_KEYS = ("gnss_protocol", "gnss_messages", "gnss_baud")  # _gnss_wire's, as UpOptions has them
_BAUDS = (4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)  # a UART's usual rates


def _cpu_list(text: str, flag: str = "--cpu-affinity") -> list[int]:
    """``--cpu-affinity 0,1`` -> [0, 1]; a bad list is one line."""
    from hil.runners.pacing import parse_cpus

    try:
        cpus = parse_cpus(text)
    except ValueError:
        raise UserError(f"{flag} {text!r}: give CPU numbers, e.g. 1 or 0,1") from None
    bad = [c for c in cpus if not 0 <= c < (os.cpu_count() or 1)]
    if bad:
        raise UserError(f"{flag} {text!r}: this machine has CPUs 0..{(os.cpu_count() or 1) - 1}")
    return cpus


def cmd_up(a: argparse.Namespace) -> int:
    from hil.bus.identity import rig_key_from_env
    from hil.bus.keys import check_name
    from hil.nav.scenario import load_scenario
    from hil.runtime.supervisor import Supervisor, UpOptions

    check_name("rig", a.rig)
    rig_key_from_env()  # a malformed HIL_RIG_KEY is one line, before anything starts
    _check_record_filter(a)
    _check_fusion_choices(a)
    scenario = load_scenario(a.scenario)  # fail here, once, with a clear message
    duration = a.duration if a.duration is not None else min(60.0, float(scenario.duration_s))
    record = a.record or _default_record_path(a.scenario)
    # Everything is checked before anything on disk changes: a refused run must leave the user's
    # earlier recording where it was (_keep_earlier_recording, last but the writability probe).
    if a.imu_rate is not None:
        from hil.nav.scenario import scenario_overrides

        scenario_overrides(scenario, imu_rate_hz=a.imu_rate)  # reject a bad rate here, with one line
    if a.dut_emulator and not a.dut:
        raise UserError("--dut-emulator needs --dut MAPPING.toml (e.g. examples/dut/navbox.toml)")
    if a.dut:
        _check_dut(a.dut)
    if a.gnss_tcp is not None:
        _check_gnss_tcp(a.gnss_tcp)
    from hil.can.bus import interface_problem

    problem = interface_problem(a.channel, a.can_interface)
    if problem:
        raise UserError(problem)
    opts = UpOptions(
        scenario=a.scenario if not Path(a.scenario).is_file() else str(Path(a.scenario).resolve()),
        duration_s=duration,
        speed=a.speed,
        record=record.resolve(),
        rig=a.rig,
        channel=a.channel,
        interface=a.can_interface,
        fd=a.fd,
        rt_priority=a.rt_priority,
        cpu_affinity=_cpu_list(a.cpu_affinity),
        sched_slice_us=a.sched_slice_us,
        rig_cpus=_cpu_list(a.rig_cpus, "--rig-cpus"),
        late_policy=a.late_policy,
        estimators=_estimators(a.estimators),
        feedback=a.feedback,
        ekf_calibration=a.ekf_calibration,
        lag_s=a.fusion_lag,
        output_predictor=not a.no_output_predictor,
        input_batch_ms=a.input_batch_ms,
        can_batch_ms=a.can_batch_ms,
        live=not a.quiet,
        log_dir=record.resolve().with_suffix(".logs"),
        restart=a.restart,
        restart_ready_s=a.restart_deadline,
        dut_mapping=str(Path(a.dut).resolve()) if a.dut else None,
        dut_emulator=a.dut_emulator,
        imu_rate_hz=a.imu_rate,
        split_mb=a.split_mb or 0.0,
        split_s=a.split_s or 0.0,
        zenoh_miss_detection=not a.no_zenoh_miss_detection,
        open_bus=a.open_bus,
        record_include=list(a.record_include),
        record_exclude=list(a.record_exclude),
        gnss_serial=str(Path(a.gnss_serial).absolute()) if a.gnss_serial else None,
        gnss_tcp=a.gnss_tcp,
        foxglove=_foxglove_listen(a.foxglove),
        **_gnss_wire(a, live=True),  # type: ignore[arg-type]
    )
    sup = Supervisor(opts)
    try:
        sup.check_options()
    except ValueError as err:
        raise UserError(str(err)) from None
    _keep_earlier_recording(record)
    _check_writable(opts.record, opts.log_dir)  # type: ignore[arg-type]  # makes the log dir: last
    _warn_loads("hil up", scenario, a, {k: getattr(opts, k) for k in _WIRE_KEYS})
    _warn_lag("hil up", scenario, a.fusion_lag, opts.duration_s)
    if not opts.gnss_protocol:
        from hil.faults import unwired_line_fault_warnings

        for line in unwired_line_fault_warnings(scenario.events, duration, "hil up"):
            print(f"hil up: warning: {line}", file=sys.stderr)
    if a.dut_emulator == "unit":
        wire = f"GNSS ({'+'.join(opts.gnss_protocol)}) on {sup.dut_line()}"
        print(f"hil up: device under test {sup.dut_command()[1]}: IMU on CAN, {wire}")
    print(
        f"hil up: rig {a.rig!r}, scenario {scenario.name!r}, {duration:g} s at speed {a.speed:g}x -> {record}"
    )
    print(f"hil up: CAN {_describe_can(a.channel, a.can_interface, sup.can_dir)}")
    print(f"hil up: {sup.endpoint_line()}", flush=True)
    if opts.foxglove:
        print(
            f"hil up: Foxglove WebSocket on ws://{opts.foxglove} (Foxglove: Open connection > Foxglove "
            f"WebSocket; layout: docs/foxglove-layout.json)",
            flush=True,
        )
    rc = sup.run()
    if sup.stop_line():
        print(f"hil up: {sup.stop_line()}", file=sys.stderr)
    if sup.ready_line():
        print(f"hil up: {sup.ready_line()}")
    if sup.ready_cpu_line():
        print(f"hil up: {sup.ready_cpu_line()}")
    if sup.cpu_table():
        print(sup.cpu_table())
    if sup.pacing_line():
        print(f"hil up: {sup.pacing_line()}")
    for line in sup.restart_log:
        print(f"hil up: restart: {line}")
    for f in sup.failures:
        print(f"hil up: FAILED: {f}", file=sys.stderr)
    described = _up_recording(record, sup.record_parts)
    return rc or described


def _up_recording(record: Path, parts: list[Path]) -> int:
    """``hil up``'s closing description of its recording; 1 when there is none, or when it shows
    that the run did not navigate (its services all up, its fusion refusing its IMU input)."""
    from hil.record.info import describe

    if not record.exists():
        print(f"hil up: no recording was written at {record}", file=sys.stderr)
        return 1
    print()
    failings: list[str] = []
    # split, or continued by a restarted recorder: the verdict is the session's last fusion
    # status, in whichever file it is (describe of a session's first file reads it there)
    print(describe(str(record), verdicts=failings))
    for f in failings:
        print(f"hil up: FAILED: {f}", file=sys.stderr)
    for part in parts:
        state = "present" if part.exists() else "MISSING"
        print(f"hil up: a restarted recorder continued in {part} ({state})")
    return 1 if failings else 0


def _check_dut(path: str) -> None:
    """``--dut``: the mapping and its DBC loaded and checked against each other now, so a bad one
    is one line before anything starts (not a run without the unit, exit 0, or a dead bridge)."""
    if not Path(path).is_file():
        raise UserError(f"--dut {path}: no such mapping file")
    from hil.can.dut_emulator import load_dut

    try:
        load_dut(path)
    except ValueError as err:
        raise UserError(f"--dut {err}") from None


def _check_gnss_tcp(text: str) -> None:
    """``--gnss-tcp HOST:PORT``: the line's own listener opened and closed now, before anything starts."""
    from hil.runners.serial import LineError, tcp_server

    try:
        tcp_server(text).close()
    except LineError as err:
        raise UserError(str(err)) from None


def _foxglove_listen(text: str | None) -> str | None:
    """``--foxglove [HOST:]PORT`` checked (and the port tried) before any process starts."""
    if text is None:
        return None
    import socket

    from hil.foxglove_server import parse_listen

    try:
        host, port = parse_listen(text)
    except ValueError as err:
        raise UserError(f"--foxglove {err}") from None
    if port == 0:  # the viewer would take any free port, which only its log names
        raise UserError(
            f"--foxglove {text}: give the port to serve on (0 picks one nobody is told), e.g. 8765"
        )
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as err:
        raise UserError(f"--foxglove {text}: cannot listen on {host}:{port}: {err.strerror}") from None
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _check_writable(record: Path, log_dir: Path) -> None:
    """The recording's directory and the log directory take a file, or one line, before any
    process starts (a recorder that cannot write would otherwise run the whole rig for nothing)."""
    for where in (record.parent, log_dir):
        try:
            where.mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(dir=where, prefix=".hil-probe-")
            os.close(fd)
            os.unlink(probe)
        except OSError as err:
            raise UserError(
                f"--record {record}: cannot write in {where} ({err.strerror or err}); "
                "give a path on a writable disk"
            ) from None


def _describe_can(channel: str, interface: str | None, can_dir: Path | None) -> str:
    """One line saying which CAN transport the IMU and bridge will use. ``can_dir``: the local
    CAN directory the supervisor decided to make (``Supervisor.can_dir``), which decides
    ``hillocal`` against ``hilzenoh`` for its children too."""
    if can_dir is not None:
        return (
            f"{channel} over the rig's local CAN sockets (hillocal) in {can_dir}, removed at exit "
            f"(a python-can tool joins with -i hillocal -c {channel} --bus-kwargs directory={can_dir})"
        )
    if interface:
        return f"{channel} over python-can interface {interface!r} (as requested)"
    if Path(f"/sys/class/net/{channel}").exists():
        return f"{channel} over SocketCAN (the kernel has {channel})"
    return (
        f"{channel} over the rig's Zenoh CAN transport (hilzenoh): this kernel has no {channel}; create "
        "one (modprobe vcan; ip link add dev vcan0 type vcan; ip link set up vcan0) to use SocketCAN"
    )


@contextlib.contextmanager
def _worker_failure(what_is_left: str) -> Iterator[None]:
    """A worker's failure said with what is left of the run (``main`` prints it in one line,
    or with the worker's traceback when it raised)."""
    try:
        yield
    except WorkerError as err:
        said = str(err)  # one line (it died), or its traceback (it raised): then a line of its own
        joint = "\nhil: " if "\n" in said else "; "
        raise WorkerError(f"{said}{joint}{what_is_left}") from None


class _StopOnSignal:
    """Ctrl-C (SIGINT) or SIGTERM during ``hil sim``: the run ends at the next window boundary
    as its end would, and the file is closed whole up to there; a second one abandons it
    (``KeyboardInterrupt``: what was flushed stays readable, ``hil recover`` finishes it)."""

    def __init__(self) -> None:
        self.signum = 0
        self._previous: dict[int, Any] = {}

    def requested(self) -> bool:
        return self.signum != 0

    def _handle(self, signum: int, _frame: object) -> None:
        if self.signum:
            raise KeyboardInterrupt
        self.signum = signum
        os.write(2, b"\nhil sim: stopping at the next second of rig time; again to abandon the file's end\n")

    def __enter__(self) -> _StopOnSignal:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():  # (only there can it listen)
            for s in (signal.SIGINT, signal.SIGTERM):
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        import signal

        for s, handler in self._previous.items():
            signal.signal(s, handler)


def cmd_sim(a: argparse.Namespace) -> int:
    from hil.bus.keys import check_name
    from hil.progress import Progress
    from hil.runners.sim import SimOptions, run_sim

    check_name("rig", a.rig)
    _check_record_filter(a)
    _check_fusion_choices(a)
    from hil.nav.scenario import load_scenario, scenario_overrides

    scenario = load_scenario(a.scenario)
    if a.imu_rate is not None:
        scenario_overrides(scenario, imu_rate_hz=a.imu_rate)  # one line if refused
    wire = _gnss_wire(a, live=False)
    _warn_loads("hil sim", scenario, a, wire)
    _warn_lag(
        "hil sim", scenario, a.fusion_lag, a.duration if a.duration is not None else scenario.duration_s
    )
    record = a.record or _default_record_path(a.scenario)
    bar = Progress("sim", unit="s rig time", enabled=False if a.quiet else None)

    def on_progress(done_s: float, total_s: float) -> None:
        bar.total = total_s
        bar.update(done_s)

    stop = _StopOnSignal()
    left = f"{record} holds what was written until then (`hil recover` finishes it)"
    with stop, bar, _worker_failure(left):
        res = run_sim(
            SimOptions(
                scenario=a.scenario,
                duration_s=a.duration,
                record=record,
                rig=a.rig,
                estimators=_estimators(a.estimators),
                feedback=a.feedback,
                ekf_calibration=a.ekf_calibration,
                output_predictor=not a.no_output_predictor,
                **({} if a.fusion_lag is None else {"lag_s": a.fusion_lag}),
                fd=a.fd,
                on_progress=on_progress,
                imu_rate_hz=a.imu_rate,
                split_mb=a.split_mb or 0.0,
                split_s=a.split_s or 0.0,
                record_include=list(a.record_include),
                record_exclude=list(a.record_exclude),
                fusion_worker=False if a.one_process else None,
                stop=stop.requested,
                **wire,  # type: ignore[arg-type]
            )
        )
    print(res.summary)
    if res.stopped_at_s is not None:
        print(
            f"hil sim: stopped by signal {stop.signum} at {res.stopped_at_s:g} s of rig time: {record} "
            f"is whole up to there (its completeness says stopped_at_s={res.stopped_at_s:g})",
            file=sys.stderr,
        )
        return 128 + stop.signum
    if not a.quiet:
        from hil.record.info import describe

        print()
        print(describe(str(record), parallel=True))
    from hil.record.info import fusion_refusals

    refused = fusion_refusals(res.fusion_counts)
    for line in refused:  # the run went to its end, but did not navigate: not a success
        print(f"hil sim: FAILED: the fusion {line}", file=sys.stderr)
    return 1 if refused else 0


def cmd_service(a: argparse.Namespace, rest: list[str]) -> int:
    from hil.bus.session import use_rig_runtime
    from hil.nodes.base import OptionsError
    from hil.runtime.registry import service_module
    from hil.runtime.service import options_from_json, run_service

    if a.name is None:
        a.parser.print_help()
        return 0 if a.help else 2
    from hil.runners.pacing import rig_cpus_from_env

    note = rig_cpus_from_env()  # hil up --rig-cpus: before any thread starts, so all inherit it
    if note:
        print(f"hil service {a.name}: {note}", file=sys.stderr)
    use_rig_runtime()  # also when compose starts it: before its first Zenoh session
    mod = service_module(a.name)
    if a.help:
        return int(mod.main(["--help"]) or 0)
    rig = service_rig(a.rig)
    if a.options is not None:
        try:
            opts = options_from_json(a.options)
        except ValueError as err:
            raise UserError(f"--options: {err}") from err
        try:
            return run_service(mod.SERVICE, rig, opts)
        except OptionsError as err:
            raise UserError(str(err)) from None
    return int(mod.main(["--rig", rig, *rest]) or 0)


def service_rig(given: str | None) -> str:
    """The rig of ``hil service NAME``: ``--rig``, else ``$HIL_RIG``, else ``default``
    (docs/environment.md), the same with ``--options`` as without; a bad name is one line."""
    from hil.bus.keys import check_name

    rig = given or os.environ.get("HIL_RIG") or "default"
    where = "--rig" if given else "HIL_RIG" if os.environ.get("HIL_RIG") else "rig"
    try:
        return check_name(where, rig)
    except ValueError as err:
        raise UserError(str(err)) from None


@contextlib.contextmanager
def _payload_errors(path: str) -> Iterator[None]:
    """A recorded payload that does not decode: one line naming the file, topic, seq and log
    time, and what to do (``hil.record.mcapio.PayloadError``)."""
    from hil.record.mcapio import PayloadError

    try:
        yield
    except PayloadError as err:
        raise UserError(err.in_file(path)) from None


def cmd_info(a: argparse.Namespace) -> int:
    from hil.record.info import describe, info_json

    accuracy = not a.no_accuracy
    with _payload_errors(a.file):
        text = (
            info_json(a.file, parallel=True) if a.json else describe(a.file, accuracy=accuracy, parallel=True)
        )
    print(text)
    return 0


def cmd_schemas(a: argparse.Namespace) -> int:
    from hil.schemas_io import check_schemas, write_schemas

    if a.write:
        for p in write_schemas():
            print(f"wrote {p}")
        return 0
    problems = check_schemas()
    for p in problems:
        print(p, file=sys.stderr)
    return 1 if problems else 0


def bench_names() -> list[str]:
    """The benchmarks ``hil bench`` runs: the modules of ``hil.bench`` with a ``main`` (read from
    their source, not imported: some load the whole rig); the others are their shared helpers."""
    import hil.bench

    here = Path(hil.bench.__file__).parent
    return sorted(
        f.stem for f in here.glob("*.py") if not f.stem.startswith("_") and "\ndef main(" in f.read_text()
    )


def cmd_bench(a: argparse.Namespace, rest: list[str]) -> int:
    import importlib

    names = bench_names()
    if a.name is None and not a.help:
        raise UserError(f"bench: name a benchmark: {', '.join(names)} (hil bench --help)")
    if a.name is None:  # hil bench --help: what it does and the benchmarks it has
        a.parser.print_help()
        print(f"\nbenchmarks: {', '.join(names)}")
        return 0
    if a.name == "list":
        print("\n".join(names))
        return 0
    if a.name not in names:
        raise UserError(f"no benchmark named {a.name!r}; the benchmarks: {', '.join(names)}")
    mod = importlib.import_module(f"hil.bench.{a.name}")
    if a.help:  # its own options, from its own parser
        return int(mod.main(["--help"]) or 0)
    from hil.progress import elapsed_progress

    # Benches that run the rig for --duration seconds know their length; the others show time.
    total = None
    if "--duration" in rest and rest.index("--duration") + 1 < len(rest):
        try:
            total = float(rest[rest.index("--duration") + 1])
        except ValueError:
            total = None
    with elapsed_progress(f"hil bench {a.name}", total):
        return int(mod.main(rest) or 0)


def cmd_campaign(a: argparse.Namespace, rest: list[str]) -> int:
    """``hil campaign ...``: many runs on Dask (hil.campaign.cli parses its own forms). Options
    before the first word land in ``rest``, the rest in ``a.args``: together, in order."""
    from hil.campaign.cli import UsageError
    from hil.campaign.cli import main as campaign_main

    try:
        return campaign_main([*rest, *a.args])
    except UsageError as err:
        raise UserError(str(err)) from None


def cmd_rerun(a: argparse.Namespace) -> int:
    from hil.progress import Progress
    from hil.record.mcapio import check_hil_recording

    check_hil_recording(a.file)
    with _payload_errors(a.file), Progress("rerun", unit="MB read") as bar:

        def on_progress(done: int, total: int) -> None:
            bar.total = total / 1e6
            bar.update(done / 1e6)

        if a.core == "timesync":  # without the fusion's modules: a tenth of its start-up
            from hil.record.rerun_timesync import rerun_timesync_report

            worker = False if a.one_process else None
            rc, lines = rerun_timesync_report(a.file, a.verify, on_progress, worker)
        else:
            from hil.record.rerun import rerun

            if a.one_process and (a.workers is not None or a.share_here):
                raise UserError(
                    "--one-process and --workers or --share-here: choose one (the fusion here, or in workers)"
                )
            if a.workers is not None and a.share_here:
                raise UserError(
                    "--workers and --share-here: choose one (--share-here: a worker and this process)"
                )
            worker = False if a.one_process else None
            split = True if a.share_here else None if a.workers is None else a.workers == 2
            here = True if a.share_here else None if a.workers is None else False
            rc, lines = rerun(
                a.file,
                core=a.core,
                verify=a.verify,
                on_progress=on_progress,
                worker=worker,
                split=split,
                here=here,
            )
    print("\n".join(lines))
    return rc


def cmd_report(a: argparse.Namespace) -> int:
    from hil.progress import Progress
    from hil.record.mcapio import check_hil_recording
    from hil.report.build import build_report

    check_hil_recording(a.file)  # one line for a corrupt, empty or foreign file, before any output
    out = a.out or Path(a.file).with_suffix(".report")
    with Progress("report", total=100.0, unit="%", enabled=False if a.no_progress else None) as bar:
        res = build_report(a.file, out, progress=lambda f, stage: bar.update(100 * f, stage=stage))
    for note in res.notes:
        print(f"hil report: note: {note}", file=sys.stderr)
    print(f"hil report: {res.html_path} ({len(res.pngs)} figures, {res.timings_s['total']:.1f} s)")
    return 0


#: how long ``hil monitor --once`` waits for a first status when no ``--duration`` is given (a rig
#: just started with ``hil up`` reports within a few seconds)
ONCE_WAIT_S = 30.0


def cmd_monitor(a: argparse.Namespace) -> int:
    import threading

    from hil.bus.keys import check_name
    from hil.monitor import MonitorOptions, connect, run_monitor
    from hil.runtime.service import install_signal_handlers

    check_name("rig", a.rig)
    session = connect(a.rig)
    stop = threading.Event()
    install_signal_handlers(stop)
    # a one-shot question gets an answer: a rig that is not there is said within ONCE_WAIT_S
    duration = a.duration if a.duration is not None or not a.once else ONCE_WAIT_S
    try:
        opts = MonitorOptions(rig=a.rig, duration_s=duration, interval_s=a.interval, once=a.once)
        return run_monitor(session, opts, stop)
    finally:
        session.close()


def cmd_foxglove(a: argparse.Namespace) -> int:
    """Serve a running rig to Foxglove over its WebSocket protocol until Ctrl-C (or --duration)."""
    import threading
    import time

    from hil.foxglove_server import FoxgloveServer, parse_listen
    from hil.monitor import connect
    from hil.runtime.service import install_signal_handlers

    try:
        host, port = parse_listen(a.listen)
    except ValueError as err:
        raise UserError(f"--listen {err}") from None
    session = connect(a.rig)
    stop = threading.Event()
    install_signal_handlers(stop)
    try:
        server = FoxgloveServer(session, a.rig, host, port)
    except OSError as err:
        session.close()
        raise UserError(f"--listen {a.listen}: {err}") from None
    supervisor = int(os.environ.get("HIL_SUPERVISOR_PID", "0") or 0)
    print(
        f"hil foxglove: rig {a.rig!r} on {server.url} (Foxglove: Open connection > Foxglove WebSocket)",
        flush=True,
    )
    t0 = time.monotonic()
    try:
        while not stop.wait(0.5):
            if a.duration is not None and time.monotonic() - t0 >= a.duration:
                break
            if supervisor and os.getppid() != supervisor:
                break  # started by hil up, which is gone: stop rather than serve nothing
    finally:
        server.close()
        session.close()
    c = server.counters
    rejected = sum(v for k, v in c.items() if k.startswith("rejected"))
    clients = c.get("relay.clients", 0) + c.get("relay.clients.first_name", 0)
    print(
        f"hil foxglove: served {c.get('messages', 0)} messages and {c.get('derived', 0)} derived on "
        f"{len(server.channels())} channels to {clients} client(s) "
        f"({c.get('relay.clients.first_name', 0)} under foxglove.websocket.v1); rejected {rejected}"
    )
    if not c.get("messages", 0):  # served nothing: say why, as hil monitor does (it said nothing, exit 0)
        from hil.bus.endpoint import viewer_bus

        _cfg, how = viewer_bus(a.rig)
        print(
            f"hil foxglove: nothing came from rig {a.rig!r} (hil/{a.rig}/...) via {how}: is it running, "
            "and (on another host) does HIL_ZENOH_CONNECT reach its router?",
            file=sys.stderr,
        )
        return 1
    return 0


def cmd_replay(a: argparse.Namespace) -> int:
    from services.replayer import run

    return run(a)


def cmd_router(a: argparse.Namespace) -> int:
    import json
    import threading

    import zenoh

    from hil.bus.session import BusConfig, open_session
    from hil.runtime.service import install_signal_handlers

    if a.config:
        # a zenohd-style json5 file (deploy/zenoh/router*.json5): its listen endpoints, TLS and
        # access control apply as written; --listen, if given, replaces the listen endpoints.
        if not Path(a.config).is_file():
            raise UserError(f"--config {a.config}: no such file")
        try:
            conf = zenoh.Config.from_file(a.config)
            conf.insert_json5("mode", json.dumps("router"))
            if a.listen:
                conf.insert_json5("listen/endpoints", json.dumps(a.listen.split(",")))
            session = zenoh.open(conf)
        except Exception as err:
            raise UserError(f"--config {a.config}: zenoh refused it: {err}") from err
        listen = a.listen or f"as in {a.config}"
    else:
        endpoints = tuple(x for x in (a.listen or ROUTER_LISTEN).split(",") if x)
        session = open_session(BusConfig(mode="router", listen=endpoints, connect=()))
        listen = ", ".join(endpoints)
    print(f"hil router: listening on {listen}", flush=True)
    stop = threading.Event()
    install_signal_handlers(stop)
    stop.wait()
    session.close()
    return 0


def cmd_fault(a: argparse.Namespace) -> int:
    """Send one ``hil.FaultCommand`` to a running rig (Zenoh from the environment, like monitor)."""
    import time

    from hil.bus.describe import encoding_of
    from hil.bus.keys import Keys, check_name
    from hil.bus.pubsub import declare_publisher
    from hil.faults import FaultError, check_fault
    from hil.messages import FaultCommand, encode
    from hil.messages import params as param_entries
    from hil.monitor import connect

    check_name("rig", a.rig)
    params: dict[str, float] = {}
    for item in a.param:
        key, sep, value = item.partition("=")
        try:
            number = float(value)
        except ValueError:
            raise UserError(f"--param {item!r}: expected NAME=NUMBER") from None
        if not sep:
            raise UserError(f"--param {item!r}: expected NAME=NUMBER")
        if key in params:
            raise UserError(f"--param {key}: given twice ({params[key]:g} and {number:g}); give it once")
        params[key] = number
    try:
        check_fault(a.kind, a.target, params, a.duration)
    except FaultError as err:
        raise UserError(str(err)) from None
    cmd = _checked_fault_command(
        FaultCommand(
            seq=time.time_ns() & (2**62 - 1),  # commands come from many short-lived senders: no counter
            stamp_ns=0,
            kind=a.kind,
            target=a.target,
            params=param_entries(params),
            duration_s=a.duration,
        )
    )
    key = Keys(a.rig).control("fault")
    session = connect(a.rig)
    try:
        # as every rig publisher, the type in its encoding
        pub = declare_publisher(session, key, encoding=encoding_of(FaultCommand))
        # a plain publisher on the key, never put to: whether anything subscribes to it (the
        # advanced one has no matching status)
        probe = session.declare_publisher(key)
        time.sleep(a.wait)  # let the session find the rig's subscribers before the one put
        heard = probe.matching_status.matching
        pub.put(encode(cmd))
        time.sleep(0.2)
    finally:
        session.close()
    if not heard:
        print(
            f"hil fault: {a.kind} went nowhere: nothing subscribes to {key} (is `hil up --rig {a.rig}` "
            f"running, and does this session reach its router: HIL_ZENOH_CONNECT, or --wait longer?)",
            file=sys.stderr,
        )
        return 1
    print(f"hil fault: sent {a.kind} to rig {a.rig!r}")
    return 0


_FAULT_FLAGS = {"kind": "KIND", "target": "--target", "params": "--param", "duration_s": "--duration"}


def _checked_fault_command(cmd: Any) -> Any:
    """``cmd`` as every subscriber will decode it, every constraint of ``hil.FaultCommand``
    checked (a constructor checks none): a command the rig would throw away as
    ``rejected.control.fault.invalid`` is refused here, naming its flag, and never sent."""
    import msgspec

    from hil.messages import FaultCommand, decode, encode

    try:
        return decode(FaultCommand, encode(cmd))
    except msgspec.ValidationError as err:
        text, _, where = str(err).rpartition(" - at `$.")
        field = where.rstrip("`").split(".")[0].split("[")[0]
        flag = _FAULT_FLAGS.get(field, field or "the command")
        value = getattr(cmd, field, None) if field in _FAULT_FLAGS else None
        shown = f" {value!r}" if isinstance(value, str) else ""
        if field == "target":  # the regex itself says little to a user
            text = "not a service or sensor name: use up to 64 of A-Z a-z 0-9 _ . -"
        raise UserError(f"{flag}{shown}: {text or err}") from None


# -- recording tools (hil.record.tools, hil.record.export): one line and exit 2 on a bad file ----


def _selection(a: argparse.Namespace) -> Any:
    from hil.record.tools import Selection

    return Selection(a.start, a.end, list(a.topics), list(a.exclude_topics))


def _recording_tool(fn: Any) -> Any:
    """A tool's bad file or option (``RecordingError``) is the user's to fix: one line, exit 2."""

    def run(a: argparse.Namespace) -> int:
        from hil.record.mcapio import RecordingError

        try:
            return int(fn(a) or 0)
        except RecordingError as err:
            raise UserError(str(err)) from None

    return run


@_recording_tool
def cmd_recover(a: argparse.Namespace) -> int:
    from hil.record.tools import recover

    res = recover(a.file, a.output)
    print("\n".join(res.lines()))
    return 0


@_recording_tool
def cmd_filter(a: argparse.Namespace) -> int:
    from hil.record.tools import filter_recording

    res = filter_recording(a.file, a.output, _selection(a))
    for note in res.notes:
        print(f"hil filter: {note}", file=sys.stderr)
    print(f"hil filter: {res.messages} messages, {res.attachments} attachments -> {res.out}")
    return 0


@_recording_tool
def cmd_merge(a: argparse.Namespace) -> int:
    from hil.record.mcapio import session_files
    from hil.record.tools import merge_recordings

    # one name: the session and its further parts
    files = session_files(a.files[0]) if len(a.files) == 1 else [Path(f) for f in a.files]
    res = merge_recordings(files, a.output)
    for note in res.notes:
        print(f"hil merge: {note}", file=sys.stderr)
    print(
        f"hil merge: {len(files)} files, {res.messages} messages, {res.attachments} attachments -> {res.out}"
    )
    return 0


@_recording_tool
def cmd_cat(a: argparse.Namespace) -> int:
    from hil.record.tools import cat

    notes: list[str] = []
    try:
        cat(a.file, _selection(a), notes=notes)
        sys.stdout.flush()
    except BrokenPipeError:  # `hil cat f | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    for note in notes:  # after the lines: a pipe's reader sees them whole, the user sees the gap
        print(f"hil cat: note: {note}", file=sys.stderr)
    return 0


@_recording_tool
def cmd_attachments(a: argparse.Namespace) -> int:
    from hil.record.tools import extract_attachments, list_attachments

    notes: list[str] = []
    if a.extract is None:
        for info in list_attachments(a.file, notes):
            print(f"{info.size:>9}  {info.media_type:<24} {info.name}")
    else:
        for path in extract_attachments(a.file, a.extract, list(a.name), notes):
            print(f"hil attachments: wrote {path}")
    for note in notes:
        print(f"hil attachments: note: {note}", file=sys.stderr)
    return 0


@_recording_tool
def cmd_export(a: argparse.Namespace) -> int:
    from hil.record.export import export

    out = a.output or Path(a.file).with_suffix(f".{a.format}")
    tables, notes = export(a.file, out, a.format, list(a.topics))
    for note in notes:
        print(f"hil export: {note}", file=sys.stderr)
    for topic, (path, rows) in sorted(tables.items()):
        print(f"{rows:>9} rows  {topic} -> {path}")
    return 0


def _add_selection_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--start", type=float, default=None, help="seconds after the first message")
    p.add_argument("--end", type=float, default=None, help="seconds after the first message (exclusive)")
    p.add_argument(
        "--topics", action="append", default=[], metavar="REGEX", help="only matching topics (repeat)"
    )
    p.add_argument(
        "--exclude-topics", action="append", default=[], metavar="REGEX", help="skip matching topics (repeat)"
    )


def _add_tool_parsers(sub: Any) -> None:
    """The recording tools (``docs/recording.md``, *Recording tools*)."""
    rc = sub.add_parser("recover", help="rewrite a crashed or truncated recording as a finished one")
    rc.add_argument("file")
    rc.add_argument("-o", "--output", type=Path, default=None, help="default: FILE.recovered.mcap")
    rc.set_defaults(func=cmd_recover)

    fl = sub.add_parser("filter", help="a time range and topics of a recording into a new file")
    fl.add_argument("file")
    fl.add_argument("-o", "--output", type=Path, required=True)
    _add_selection_args(fl)
    fl.set_defaults(func=cmd_filter)

    mg = sub.add_parser("merge", help="split parts (or filtered pieces) into one indexed file")
    mg.add_argument("files", nargs="+", help="inputs; one name: that recording and its _0001... parts")
    mg.add_argument("-o", "--output", type=Path, required=True)
    mg.set_defaults(func=cmd_merge)

    ct = sub.add_parser("cat", help="messages as JSON lines")
    ct.add_argument("file")
    _add_selection_args(ct)
    ct.set_defaults(func=cmd_cat)

    at = sub.add_parser("attachments", help="list or extract the embedded scenario, DBC, schemas")
    at.add_argument("file")
    at.add_argument("--extract", type=Path, default=None, metavar="DIR", help="write them under DIR")
    at.add_argument("--name", action="append", default=[], help="only this attachment (repeat)")
    at.set_defaults(func=cmd_attachments)

    ex = sub.add_parser("export", help="IMU, GNSS, truth and nav as CSV or Parquet tables")
    ex.add_argument("file")
    ex.add_argument("--format", choices=["csv", "parquet"], default="csv")
    ex.add_argument("-o", "--output", type=Path, default=None, help="directory (default: FILE.<format>/)")
    ex.add_argument("--topics", action="append", default=[], metavar="REGEX", help="only matching topics")
    ex.set_defaults(func=cmd_export)


def _add_up_parser(sub: Any) -> None:
    """``hil up``'s options (the live rig)."""
    up = sub.add_parser("up", help="run the live rig: every service as its own process")
    _add_run_args(up, None)
    _add_fusion_args(up)
    up.add_argument("--speed", type=speed, default=1.0, help="rig clock K times faster than real time")
    up.add_argument("--channel", default="vcan0", help="CAN channel of the IMU")
    up.add_argument(
        "--can-interface",
        default=None,
        help="python-can interface (default: socketcan if the channel exists, else hillocal on one "
        "machine, hilzenoh when joining a router)",
    )
    up.add_argument("--fd", action="store_true", help="CAN FD: one frame per IMU sample")
    up.add_argument(
        "--rt-priority",
        type=bounded_int(0, 99),
        default=0,
        help="SCHED_FIFO priority (1-99) of the IMU's frame sender where permitted (docs/timing.md)",
    )
    up.add_argument(
        "--cpu-affinity",
        default="",
        help="CPUs to pin the IMU's frame sender to, e.g. 1 or 0,1 (default: any)",
    )
    up.add_argument(
        "--rig-cpus",
        default="",
        help="CPUs for every process of the rig but the IMU's frame sender, e.g. 0 (default: any); "
        "with --cpu-affinity on another, the sender has a CPU of its own (docs/timing.md)",
    )
    up.add_argument(
        "--sched-slice-us",
        type=bounded_int(0, 100_000),
        default=100,
        help="the IMU's frame sender's scheduler time slice at normal priority, µs (Linux 6.12+, "
        "no privilege needed: it preempts on its tick; default 100, 0: the kernel's; docs/timing.md)",
    )
    up.add_argument(
        "--late-policy",
        choices=("send", "skip"),
        default="send",
        help="an IMU sample whose tick the host missed: send it late (default) or skip its slot",
    )
    up.add_argument(
        "--restart", type=restart_count, default=0, help="restarts allowed per service before the run fails"
    )
    up.add_argument(
        "--restart-deadline",
        type=bounded_float(1.0, 3600.0, unit="s"),
        default=60.0,
        help="seconds a restarted service has to report running; later, the run fails (default 60)",
    )
    up.add_argument(
        "--input-batch-ms",
        type=bounded_float(0.0, 100.0, unit="ms"),
        default=0.0,
        help="time sync and fusion take their inputs in batches this many ms apart: fewer wake-ups "
        "(less CPU) for up to twice this much more latency on the fused output (default 0: each at once)",
    )
    up.add_argument(
        "--can-batch-ms",
        type=bounded_float(0.0, 100.0, unit="ms"),
        default=None,  # UpOptions.can_batch_ms (test_input_batch_options: the same)
        help="the CAN bridge reads the IMU's frames in windows this many ms apart and publishes "
        "each window's samples as one message: fewer messages and wake-ups in every service for up "
        "to this much more latency downstream of the bridge; the wire and the samples' receive "
        "stamps are unchanged (default: 20 up to 500 Hz, 10 above; 0: each sample at once)",
    )
    up.add_argument("--quiet", action="store_true", help="no live table")
    up.add_argument("--dut", default=None, help="device under test on the CAN bus: its mapping TOML")
    up.add_argument(
        "--dut-emulator",
        nargs="?",
        const="unit",
        default=None,
        choices=("unit", "truth"),
        help="also play the unit for --dut: 'unit' (the default) runs the mapping's own program on the "
        "wires (examples/dut/navbox.py: IMU on CAN, its own GNSS line, default --gnss-protocol nmea), "
        "'truth' a stand-in sending truth plus a wandering error (docs/dut.md)",
    )
    up.add_argument(
        "--open-bus",
        action="store_true",
        help="let any local process join the embedded hub without the per-run credential "
        "(it still listens on loopback only; docs/deploy.md, Security)",
    )
    up.add_argument(
        "--no-zenoh-miss-detection",
        action="store_true",
        help="plain Zenoh publishers and a plain recorder subscriber (seq gaps remain the loss measure)",
    )
    _add_gnss_wire_args(up)
    up.add_argument(
        "--gnss-serial", default=None, help="PATH: the receiver's line as a pseudo-terminal linked there"
    )
    up.add_argument("--gnss-tcp", default=None, help="HOST:PORT: the receiver's line served over TCP")
    up.add_argument(
        "--foxglove",
        nargs="?",
        const="8765",
        default=None,
        metavar="[HOST:]PORT",
        help="serve the rig to Foxglove over WebSocket (hil foxglove) on this port (default 8765, loopback)",
    )
    up.set_defaults(func=cmd_up)


def _add_rerun_parser(sub: Any) -> None:
    rr = sub.add_parser("rerun", help="recompute a core's outputs from a recording's inputs")
    rr.add_argument("file")
    rr.add_argument("--core", choices=["fusion", "timesync"], default="fusion")
    rr.add_argument("--verify", action="store_true", help="exit 0 only if every output is bit-identical")
    rr.add_argument(
        "--one-process",
        action="store_true",
        help="keep the core in this process (default on 2+ CPUs: a worker for the fusion of 3+ "
        "estimators, or the time sync, recomputing while this one reads; the same bits)",
    )
    rr.add_argument(
        "--workers",
        type=int,
        choices=(1, 2),
        default=None,
        help="fusion workers: 1 runs every estimator; 2 share them, the first running the GNSS "
        "gate's reference and handing its verdicts to the second (default: 2 on 3+ CPUs for 4+ "
        "estimators; on 2 CPUs see --share-here; the same bits)",
    )
    rr.add_argument(
        "--share-here",
        action="store_true",
        help="one worker with the gate's reference, and this process running the two lightest "
        "estimators beside its reading (the default on 2 CPUs for 4+ estimators with filters in "
        "feedback form or ekf15's calibration states: a consumer IMU's; the same bits)",
    )
    rr.set_defaults(func=cmd_rerun)


def _add_service_parser(sub: Any) -> None:
    svc = sub.add_parser("service", help="run one service alone (what docker compose runs)", add_help=False)
    svc.add_argument("name", nargs="?", help="a service; `hil service NAME --help` lists its flags")
    svc.add_argument("-h", "--help", action="store_true", help="this help, or NAME's flags")
    svc.add_argument("--rig", default=None)
    svc.add_argument("--options", default=None, help="service options as a JSON object")
    svc.set_defaults(func=cmd_service, passthrough=True, parser=svc)


def _add_fault_parser(sub: Any) -> None:
    """``hil fault``: its bounds are ``hil.FaultCommand``'s own."""
    # not hil.faults: numpy is ~0.1 s of every command
    from hil.sensor_table import FAULT_KINDS, FAULT_MAX_DURATION_S

    flt = sub.add_parser("fault", help="inject a fault into a running rig (recorded as events)")
    flt.add_argument("kind", choices=sorted(FAULT_KINDS))
    flt.add_argument("--rig", default="bench", help="the rig (hil/<rig>/control/fault)")
    flt.add_argument("--target", default="", help="kill_service: the service; clock_step: imu or gnss")
    flt.add_argument(
        "--duration",
        type=bounded_float(0.0, FAULT_MAX_DURATION_S, unit="s"),  # hil.FaultCommand's own bound
        default=0.0,
        help="seconds (0: to the end / instantaneous)",
    )
    flt.add_argument("--param", action="append", default=[], help="NAME=NUMBER, e.g. percent=20 (repeatable)")
    flt.add_argument(
        "--wait",
        type=bounded_float(0.0, 60.0, unit="s"),
        default=1.0,
        help="seconds to connect before sending",
    )
    flt.set_defaults(func=cmd_fault)


def _add_bench_parser(sub: Any) -> None:
    """``hil bench``: its -h is its own, so ``hil bench NAME --help`` reaches the benchmark's parser."""
    bench = sub.add_parser(
        "bench",
        add_help=False,
        help="run a benchmark and write docs/benchmarks.md",
        description="Run one benchmark (its own options: hil bench NAME --help); it prints its figures "
        "and writes its section of docs/benchmarks.md, with the command that produced them.",
    )
    bench.add_argument("name", nargs="?", help="the benchmark (hil bench list: their names)")
    bench.add_argument(
        "-h", "--help", action="store_true", help="this help and the benchmarks, or NAME's options"
    )
    bench.set_defaults(func=cmd_bench, passthrough=True, parser=bench)


def build_parser(service_only: bool = False) -> argparse.ArgumentParser:
    """Every command's parser; ``service_only``: ``hil service``'s alone (it parses the same)."""
    ap = OneLineParser(prog="hil", description="INS/GNSS hardware-in-the-loop rig over Zenoh")
    ap.add_argument("--version", action="version", version=f"hil {__version__}")
    sub = ap.add_subparsers(dest="cmd", required=True)
    if service_only:
        _add_service_parser(sub)
        return ap

    _add_up_parser(sub)

    sim = sub.add_parser("sim", help="the same cores in one process on a virtual clock, as fast as possible")
    _add_run_args(sim, None)
    sim.add_argument(
        "--fd",
        action="store_true",
        help="CAN FD: one frame per IMU sample (classic CAN: four; docs/can-protocol.md)",
    )
    _add_fusion_args(sim)
    _add_gnss_wire_args(sim)
    sim.add_argument("--quiet", action="store_true")
    sim.add_argument(
        "--one-process",
        action="store_true",
        help="run every node in this process (default on 2+ CPUs: a worker runs the fusion, and "
        "with a light fusion the CAN bridge, GNSS emulator and time sync too; the same file)",
    )
    sim.set_defaults(func=cmd_sim)

    _add_service_parser(sub)

    info = sub.add_parser("info", help="what a recording holds")
    info.add_argument("file")
    info.add_argument("--json", action="store_true")
    info.add_argument("--no-accuracy", action="store_true")
    info.set_defaults(func=cmd_info)

    sch = sub.add_parser("schemas", help="check (default) or --write schemas/ from the message types")
    sch.add_argument("--write", action="store_true")
    sch.set_defaults(func=cmd_schemas)

    _add_bench_parser(sub)

    _add_rerun_parser(sub)

    camp = sub.add_parser(
        "campaign", add_help=False, help="Monte-Carlo sims and rerun libraries on Dask (docs/campaigns.md)"
    )
    camp.add_argument("args", nargs=argparse.REMAINDER)
    camp.set_defaults(func=cmd_campaign, passthrough=True)

    rep = sub.add_parser(
        "report", help="an HTML report (and PNGs) of a recording: accuracy, faults, sync, loss, CAN"
    )
    rep.add_argument("file")
    rep.add_argument("--out", type=Path, default=None, help="output directory (default: FILE.report/)")
    rep.add_argument("--no-progress", action="store_true", help="no progress bar")
    rep.set_defaults(func=cmd_report)

    mon = sub.add_parser("monitor", help="attach to a running rig (another terminal or host): the live table")
    mon.add_argument("--rig", default="bench", help="the rig to watch (hil/<rig>/...)")
    mon.add_argument("--duration", type=seconds, default=None, help="stop after this many seconds")
    mon.add_argument("--interval", type=positive_float, default=1.0, help="seconds between redraws")
    mon.add_argument(
        "--once",
        action="store_true",
        help=f"print one table once statuses arrive, then exit; exit 1 if none came within --duration "
        f"(with --once, {ONCE_WAIT_S:g} s unless given)",
    )
    mon.set_defaults(func=cmd_monitor)

    fox = sub.add_parser(
        "foxglove", help="serve a running rig to Foxglove (WebSocket), attached like hil monitor"
    )
    fox.add_argument("--rig", default="bench", help="the rig to serve (hil/<rig>/...)")
    fox.add_argument(
        "--listen",
        default="127.0.0.1:8765",
        help="[HOST:]PORT of the Foxglove WebSocket server (default 127.0.0.1:8765: loopback only)",
    )
    fox.add_argument("--duration", type=positive_float, default=None, help="stop after this many seconds")
    fox.set_defaults(func=cmd_foxglove)

    from services.replayer import add_args as add_replay_args

    rp = sub.add_parser("replay", help="republish a recording onto Zenoh (and its CAN frames onto a bus)")
    add_replay_args(rp)
    rp.set_defaults(func=cmd_replay)

    _add_fault_parser(sub)

    _add_tool_parsers(sub)

    router = sub.add_parser("router", help="run a Zenoh router (for several hosts or compose)")
    router.add_argument(
        "--listen",
        default=None,
        help="endpoints, comma-separated (default: --config's, else tcp/127.0.0.1:7447, this host only; "
        "tcp/0.0.0.0:7447 for other hosts)",
    )
    router.add_argument("--config", default=None, help="a zenoh json5 config file (TLS, access control)")
    router.set_defaults(func=cmd_router)
    return ap


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the program itself, not a caller with arguments of its own (a test)
        heap.command_process = True
        # Every hil process is one of several on the machine (a service among the rig's, a sim
        # or a rerun beside its forked worker), its matrices tiny (15x15 at most): OpenBLAS's
        # threads would only compete with them, and starting them costs ~40 ms of CPU at
        # numpy's import (before a service can say ready; in a sim's start-up). Set it to use more.
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    argv = sys.argv[1:] if argv is None else argv
    # `hil service NAME` is every process of `hil up`, whose start-up time zero waits for: the
    # whole command line's parsers (hil.faults, numpy with it) cost it ~0.2 s of CPU
    ap = build_parser(service_only=argv[:1] == ["service"])
    a, rest = ap.parse_known_args(argv)
    if rest and not getattr(a, "passthrough", False):
        ap.error(f"unrecognized arguments: {' '.join(rest)}")
    try:
        rc = int((a.func(a, rest) if getattr(a, "passthrough", False) else a.func(a)) or 0)
        sys.stdout.flush()  # a closed pipe is found here, not at exit
        return rc
    except BrokenPipeError:
        # `hil info f | head`: the reader has what it wanted; end quietly, as `hil cat` does
        # (stdout onto devnull, so Python's flush at exit does not report it again)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        return 130
    except UserError as err:
        print(f"hil: {err}", file=sys.stderr)
        return EXIT_USAGE
    except WorkerError as err:  # a worker process that died or failed: the run did not finish
        print(err, file=sys.stderr)
        return 1
    except (FileNotFoundError, ValueError, KeyError, OSError) as err:
        # boundary errors from loaders carry the facts; show them as one line (a recording's or
        # a scenario's error names the file or key and what to do already: its class name adds
        # nothing)
        from hil.nav.scenario import ScenarioError  # here: not in every command's start
        from hil.record.mcapio import RecordingError

        msg = _message(err)
        said = msg if isinstance(err, RecordingError | ScenarioError) else f"{type(err).__name__}: {msg}"
        print(f"hil: {said}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
