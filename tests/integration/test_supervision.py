"""Supervision for real: `hil up --restart N` with services SIGKILLed mid-run (real processes, real
Zenoh). A killed service is restarted and rejoins the run at the current rig time, the restart is
an `hil.Event` in the recording, a killed recorder continues in `<stem>.part1.mcap`, and a service
that keeps dying ends the run non-zero with the reason."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path
from typing import ClassVar

import pytest

from hil.bus.session import BusConfig, open_session
from hil.messages import Event, RunInfo, ServiceStatus, decode
from hil.record.mcapio import Record, read_session
from hil.runtime.clock import RigClock
from tests.conftest import REPO, free_port, hil_cmd

pytestmark = pytest.mark.slow


class Rig:
    """`hil up` on its own hub; service pids come from their own ServiceStatus messages.

    A rig a failed test did not finish is stopped and its hub closed by ``close_all`` in the
    teardown (tests/integration/conftest.py): an open hub's callback thread kept pytest from
    exiting once."""

    live: ClassVar[list[Rig]] = []

    def __init__(self, rig: str, out: Path, *args: str) -> None:
        Rig.live.append(self)
        self.rig = rig
        self.endpoint = endpoint = f"tcp/127.0.0.1:{free_port()}"
        # a router, its services clients: the layout of hil up's embedded hub
        self.hub = open_session(BusConfig(mode="router", listen=(endpoint,), connect=()))
        self.status: dict[str, ServiceStatus] = {}
        self.events: set[tuple[str, str]] = set()  # (source, kind) seen on the bus
        self.hub.declare_subscriber(f"hil/{rig}/event/*", self._on_event)
        self.lock = threading.Lock()
        self.hub.declare_subscriber(f"hil/{rig}/status/*", self._on_status)
        self.run: RunInfo | None = None
        self.hub.declare_subscriber(f"hil/{rig}/run", self._on_run)
        env = dict(os.environ, HIL_ZENOH_MODE="client", HIL_ZENOH_CONNECT=endpoint, HIL_ZENOH_LISTEN="")
        self.proc = subprocess.Popen(
            hil_cmd("up", "--record", str(out), "--quiet", "--rig", rig, *args),
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def _on_status(self, sample: object) -> None:
        st = decode(ServiceStatus, sample.payload.to_bytes())  # type: ignore[attr-defined]
        with self.lock:
            self.status[st.service] = st

    def _on_event(self, sample: object) -> None:
        ev = decode(Event, sample.payload.to_bytes())  # type: ignore[attr-defined]
        with self.lock:
            self.events.add((ev.source, ev.kind))

    def wait_events(self, *wanted: tuple[str, str], timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if set(wanted) <= self.events:
                    return
            assert self.proc.poll() is None, self.status
            time.sleep(0.2)
        raise AssertionError(f"never saw {set(wanted) - self.events} on the bus; saw {self.events}")

    def _on_run(self, sample: object) -> None:
        self.run = decode(RunInfo, sample.payload.to_bytes())  # type: ignore[attr-defined]

    def rig_time_s(self) -> float:
        """The rig's time now (0 before its run starts)."""
        run = self.run
        return RigClock(run.start_epoch_ns, run.speed).now_ns() / 1e9 if run is not None else 0.0

    def reach(self, t_s: float) -> None:
        """Wait until the run is at rig time ``t_s``: a service reports running before the run's
        time zero, and a command sent then lands before the run (the outage a CI run once
        commanded covered the first 2 s, not a hole in the fixes)."""
        deadline = time.monotonic() + t_s + 180.0
        while self.rig_time_s() < t_s:
            assert self.proc.poll() is None and time.monotonic() < deadline, self.status
            time.sleep(0.1)

    def stop_at(self, t_s: float, timeout: float = 120.0) -> tuple[int, str, str]:
        """Let the run reach rig time ``t_s``, then stop it as Ctrl-C does, and ``finish``.

        For a run started with a --duration longer than the test: what the test does first (start
        commands, wait for restarts) takes what the machine's load makes it take, and the run
        cannot end before the test has done it; an idle machine does not wait out a margin."""
        self.reach(t_s + 0.3)  # as --duration stops: 0.3 s past the end
        self.proc.send_signal(signal.SIGINT)
        return self.finish(timeout)

    def running_pid(self, service: str, not_pid: int = -1, timeout: float = 90.0) -> int:
        """Pid of ``service`` once it reports running (and is not ``not_pid``)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                st = self.status.get(service)
            if st is not None and st.state == "running" and st.pid != not_pid:
                return st.pid
            assert self.proc.poll() is None, self.proc.communicate()
            time.sleep(0.1)
        raise AssertionError(f"{service} never ran (pid != {not_pid}): {self.status.get(service)}")

    def finish(self, timeout: float = 120.0) -> tuple[int, str, str]:
        try:
            out, err = self.proc.communicate(timeout=timeout)
        finally:
            self.close()
        return self.proc.returncode, out, err

    def close(self) -> None:
        """Stop ``hil up`` (SIGTERM: it stops its services; SIGKILL if it does not within 60 s)
        and close the hub. Safe to repeat."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.communicate()
        if not self.hub.is_closed():
            self.hub.close()
        if self in Rig.live:
            Rig.live.remove(self)

    @classmethod
    def close_all(cls) -> None:
        for rig in list(cls.live):
            rig.close()


def _events(*paths: Path) -> list[Event]:
    out: list[Event] = []
    for p in paths:
        s = read_session(p)
        out += [decode(Event, r.payload) for r in s.records if r.schema == "hil.Event"]
    return out


def _rerun_verify(path: Path, core: str) -> subprocess.CompletedProcess[str]:
    """``hil rerun PATH --core CORE --verify``, as a user runs it."""
    cmd = hil_cmd("rerun", str(path), "--core", core, "--verify")
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)


def _seq(r: Record) -> int:
    """The payload's seq (generation included; MCAP's ``sequence`` holds its low 32 bits only)."""
    return int(r.decode().seq)  # type: ignore[attr-defined]


def test_killed_services_are_restarted_rejoin_the_run_and_are_recorded(tmp_path: Path) -> None:
    # GIVEN a 14 s run that allows one restart per service
    out = tmp_path / "s.mcap"
    rig = Rig("suprig", out, "--duration", "600", "--restart", "1")  # stopped at 14 s or later
    # WHEN the GNSS receiver and the fusion are SIGKILLed early, the recorder later
    killed = {svc: rig.running_pid(svc) for svc in ("gnss_emulator", "fusion")}
    for pid in killed.values():
        os.kill(pid, signal.SIGKILL)
    for svc, pid in killed.items():
        rig.running_pid(svc, not_pid=pid)
    # the recorder dies only once the first part holds what the restarts said: their events went
    # out, then a flush (1 s) wrote them (a fixed pause once lost the fusion's "realigned" in the
    # killed recorder's unflushed chunk)
    rig.wait_events(("gnss_emulator", "resumed"), ("fusion", "realigned"))
    time.sleep(2.5)
    recorder = rig.running_pid("recorder")
    os.kill(recorder, signal.SIGKILL)
    rig.running_pid("recorder", not_pid=recorder)
    rc, stdout, stderr = rig.stop_at(max(14.0, rig.rig_time_s() + 6.0))
    # THEN the run completes, says what happened, and the recorder went on in a new part
    assert rc == 0, stdout[-3000:] + stderr[-3000:]
    # Ctrl-C before --duration: a clean stop (exit 0) that the summary says cut the run short
    assert re.search(r"hil up: stopped by SIGINT at \d+\.\d s of the 600 s asked", stderr), stderr[-3000:]
    assert "gnss_emulator died (killed by signal 9); restarted (1/1)" in stdout
    assert re.search(r"restart: fusion ready again \(pid \d+\) after [\d.]+ s down", stdout), stdout[-3000:]
    part = tmp_path / "s.part1.mcap"
    assert f"recording continues in {part}" in stdout and part.is_file()
    first = read_session(out)
    assert first.truncated  # the killed recorder's file reads up to its last flushed chunk
    events = _events(out, part)
    restarted = {e.source for e in events if e.kind == "service_restarted"}
    assert {"gnss_emulator", "fusion"} <= restarted, events
    kinds = {(e.source, e.kind) for e in events}
    assert ("gnss_emulator", "resumed") in kinds and ("fusion", "realigned") in kinds, kinds
    # the two files end to end hold each message once: the restarted recorder asked the
    # publishers' caches for their history and wrote none of what the killed one's file holds
    # (a cache's replay once put truth from seq 410 and every GNSS fix in both files)
    both = [read_session(out), read_session(part)]
    topics = {t for s in both for t, schema in s.topics().items() if schema.startswith("hil.")}
    seqs = {t: [_seq(r) for s in both for r in s.by_topic(t)] for t in topics}
    for topic in ("sensor/gnss", "capture/gnss", "nav/ekf15", "nav/ins", "truth", "sensor/imu"):
        assert seqs[f"hil/suprig/{topic}"], topic
    dups = {t: [k for k, n in Counter(v).items() if n > 1][:10] for t, v in seqs.items()}
    assert not {t: d for t, d in dups.items() if d}, dups
    comp = both[1].meta("completeness", "topics")
    cont = both[1].meta("completeness", "continues")
    assert cont["files"] == [out.name] and cont["messages"] == sum(
        1 for r in both[0].records if r.schema.startswith("hil.")
    ), cont
    # (the GNSS fixes since the start are in its cache: replayed, they are known, not written)
    assert cont["already_recorded"] > 0, cont
    # the part's accounting covers the whole session: what neither file holds is missing there
    # (``first`` is the first seen: a status the first recorder missed at its start can come
    # later, from the cache, into the part)
    for topic, v in seqs.items():
        tr = comp[topic]
        assert tr["count"] == len(v) and tr["duplicates"] == 0, (topic, tr)
        if not tr["restarts"]:
            assert tr["missing"] == len(set(range(tr["first"], max(v) + 1)) - set(v)), (topic, tr)
    # and what the caches held of the recorder's downtime is in the part: the 1 Hz statuses of
    # services that were not restarted are whole from their first (their caches span minutes;
    # a status 0 the first recorder missed at its start came from the cache into the part)
    for svc in ("world", "imu_emulator", "can_bridge", "timesync"):
        v, tr = seqs[f"hil/suprig/status/{svc}"], comp[f"hil/suprig/status/{svc}"]
        assert sorted(v) == list(range(max(v) + 1)) and tr["missing"] == 0, (svc, tr)
    # the restarted fusion publishes finite solutions on the same run
    assert len(both[1].by_topic("hil/suprig/nav/ekf15")) > 50
    # no service log holds a traceback
    for log in (tmp_path / "s.logs").glob("*.log"):
        assert "Traceback" not in log.read_text(errors="replace"), log
    # and no service, restarted or not, published a message the recorder refused (a GNSS receiver
    # restarted before time zero put a PPS time tag with seq -1 on the bus)
    for sess in both:
        st = decode(ServiceStatus, sess.by_topic("hil/suprig/status/recorder")[-1].payload)
        refused = {c.key: c.value for c in st.counters if c.key.startswith("rejected.") and c.value}
        assert not refused, (refused, st.last_error)
    # and the session reruns whole from its first file, bit for bit: the killed recorder's file up
    # to its cut, then the restarted one's part, and the fusion in its two lives (once, rerun read
    # the first file only, and the part alone has no fusion configuration)
    # (the recorder's downtime can lose fusion inputs the caches no longer held: the fusion's
    # outputs after them cannot be recomputed, and verify says so and compares those before; the
    # GNSS fixes have a gap of their own, the receiver's death, which the fusion never had)
    lost = comp["hil/suprig/synced/imu"]["missing"]
    said = {}
    for core in ("fusion", "timesync"):
        res = _rerun_verify(out, core)
        said[core] = res.stdout + res.stderr
        assert "continued by a restarted recorder in s.part1.mcap: reran" in res.stdout, said[core]
        assert "s.mcap is cut short" in res.stdout and "the file is truncated" not in res.stdout, said[core]
        assert res.returncode == 0 and "VERIFY OK" in res.stdout, said[core]
        if core == "fusion":
            assert ("the recording lacks inputs the live fusion took" in res.stdout) == bool(lost), said[core]
    assert "the fusion restarted 1 time(s)" in said["fusion"], said["fusion"]


def test_a_service_that_keeps_dying_ends_the_run_non_zero_with_the_reason(tmp_path: Path) -> None:
    out = tmp_path / "d.mcap"
    # a run far longer than the test may take: only the failure can end it in time
    rig = Rig("dierig", out, "--duration", "3600", "--restart", "1")
    pid = rig.running_pid("imu_emulator")
    os.kill(pid, signal.SIGKILL)
    os.kill(rig.running_pid("imu_emulator", not_pid=pid), signal.SIGKILL)
    rc, _stdout, stderr = rig.finish(timeout=180)  # TimeoutExpired if it went on
    assert rc != 0
    assert "imu_emulator died (killed by signal 9) after 1 restart(s) of 1 allowed" in stderr, stderr[-2000:]
    kinds = {(e.source, e.kind) for e in _events(out)}
    assert ("imu_emulator", "service_restarted") in kinds and ("imu_emulator", "run_failed") in kinds


def test_a_restart_reads_as_a_restart_in_the_completeness_and_the_downtime_as_loss(tmp_path: Path) -> None:
    # GIVEN a run allowing one restart, in which the bridge and timesync have published for a while
    out = tmp_path / "g.mcap"
    rig = Rig("genrig", out, "--duration", "14", "--restart", "1")
    pids = {svc: rig.running_pid(svc) for svc in ("can_bridge", "timesync")}
    time.sleep(3.0)
    # WHEN both are SIGKILLed (the recorder keeps recording) and come back
    t_kill = time.monotonic()
    for pid in pids.values():
        os.kill(pid, signal.SIGKILL)
    for svc, pid in pids.items():
        rig.running_pid(svc, not_pid=pid)
    # from the kill until the test saw both running again: no shorter than the bridge's downtime,
    # however long a loaded machine makes a restart (once 8.4 s, with two CPU hogs at load 18)
    down_s = time.monotonic() - t_kill
    rc, stdout, stderr = rig.finish()
    assert rc == 0, stdout[-3000:] + stderr[-3000:]
    s = read_session(out)
    topics = s.meta("completeness", "topics")
    # THEN each of their publishers reads as restarted once, in a second generation counted from
    # 0 again: no duplicates, no disorder and no loss charged to the restart itself
    bridge_pubs = ("status/can_bridge", "event/can_bridge", "can/vcan0", "timetag/imu")
    timesync_pubs = ("status/timesync", "clock/imu", "clock/gnss")
    restarted = {f"hil/genrig/{t}" for t in (*bridge_pubs, *timesync_pubs)}
    assert {k for k, v in topics.items() if v["restarts"]} == restarted, topics
    for key in restarted:
        tr = topics[key]
        assert (tr["restarts"], tr["generation"], tr["duplicates"], tr["out_of_order"]) == (1, 1, 0, 0), (
            key,
            tr,
        )
        assert [g["generation"] for g in tr["generations"]] == [0, 1] and tr["missing"] == 0, (key, tr)
    assert not [k for k, v in topics.items() if v["duplicates"]], topics
    # ... while what nobody delivered during the downtime is loss: one gap in the IMU samples the
    # dead bridge did not decode (a few seconds at 400 Hz) and in the fixes timesync did not re-stamp,
    # and the restarted bridge reused no sample seq (it waits for the device's SampleCount)
    imu = topics["hil/genrig/sensor/imu"]
    assert (imu["restarts"], imu["gaps"], imu["duplicates"], imu["out_of_order"]) == (0, 1, 0, 0), imu
    ((a, b),) = imu["gap_ranges"]
    # (a: the kill comes some seconds after the bridge runs; the run's time zero is later than
    # that by the rig's start-up, so only "well after the first samples" is a safe bound; the gap
    # is the downtime the test measured, plus 2 s for the dead bridge's backlog and the new one's
    # wait for a SampleCount)
    assert 100 < imu["missing"] == b - a + 1 < (down_s + 2.0) * 400 and a > 100, (imu, down_s)
    gnss = topics["hil/genrig/synced/gnss"]
    assert gnss["restarts"] == 0 and gnss["gaps"] >= 1 and gnss["missing"] > 0, gnss
    assert s.meta("completeness", "replay_ready") is False  # data was lost: honest
    bridge = [decode(ServiceStatus, r.payload) for r in s.by_topic("hil/genrig/status/can_bridge")]
    assert bridge[-1].counter_map().get("dropped.can.unindexed_samples", 0) < 40
    # the restarts are on record, and hil info says so instead of showing duplicates
    kinds = {(e.source, e.kind) for e in _events(out)}
    assert ("can_bridge", "service_restarted") in kinds and ("timesync", "service_restarted") in kinds
    info = subprocess.run(hil_cmd("info", str(out)), cwd=REPO, capture_output=True, text=True, timeout=120)
    assert info.returncode == 0, info.stderr
    assert "restarts:  7 publisher(s) restarted during the recording" in info.stdout, info.stdout
    rows = [ln.split() for ln in info.stdout.splitlines() if ln.startswith("hil/genrig/")]
    assert rows and all(r[5] == "0" for r in rows), info.stdout  # the dups column
    # and the restarted time sync named the first input of each sensor it took, from which the
    # time-sync rerun rebuilds it: every re-stamp of both lives is compared (once the later life's
    # were counted as not verifiable; before that, fed to the first life's core, verify failed
    # right after the restart with no word of it)
    named = [e.detail for e in _events(out) if (e.source, e.kind) == ("timesync", "first_input")]
    assert sorted(d.split(" re-stamps ")[1].split()[0] for d in named) == ["gnss", "imu"], named
    res = _rerun_verify(out, "timesync")
    assert res.returncode == 0, res.stdout + res.stderr
    note = re.search(
        r"note: the time sync restarted at t=[\d.]+ s .*: its (\d+) re-stamps after that compared", res.stdout
    )
    ok = re.search(r"VERIFY OK: all (\d+) recorded re-stamps", res.stdout)
    assert note and ok and int(note[1]) > 0, res.stdout
    recorded = sum(len(s.by_topic(f"hil/genrig/synced/{k}")) for k in ("imu", "gnss"))
    assert int(ok[1]) == recorded, (res.stdout, recorded)


def _with_event_before_sample(records: list[Record], event: Record, imu_seq: int) -> list[Record]:
    """``records`` with ``event`` moved to just before the synced IMU sample ``imu_seq``: the
    recorder can take the restarted fusion's event before the time sync's sample it names."""
    rest = [r for r in records if r is not event]
    at = next(
        i
        for i, r in enumerate(rest)
        if r.topic.endswith("/synced/imu") and int(r.decode().seq) == imu_seq  # type: ignore[attr-defined]
    )
    return [*rest[:at], event, *rest[at:]]


def test_a_restarted_fusion_reruns_bit_identical_from_its_realignment(tmp_path: Path) -> None:
    # GIVEN a run whose fusion is SIGKILLed a few seconds in and restarted (it re-aligns from
    # truth at the first IMU sample it takes and says so in a realigned event)
    out = tmp_path / "f.mcap"
    rig = Rig("rerunrig", out, "--duration", "600", "--restart", "1")
    pid = rig.running_pid("fusion")
    rig.reach(3.0)
    os.kill(pid, signal.SIGKILL)
    rig.running_pid("fusion", not_pid=pid)
    rig.wait_events(("fusion", "realigned"))
    rc, stdout, stderr = rig.stop_at(rig.rig_time_s() + 4.0)
    assert rc == 0, stdout[-3000:] + stderr[-3000:]
    # WHEN it is rerun
    res = _rerun_verify(out, "fusion")
    # THEN both lives of the fusion are recomputed bit for bit: the first on the inputs before the
    # restart, the second from its re-alignment on the inputs it took (once, the second life was
    # rerun on every input from the alignment on, and its first outputs were an interval ahead)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "note: the fusion restarted 1 time(s)" in res.stdout, res.stdout
    assert "VERIFY OK" in res.stdout, res.stdout
    # ... with the event recorded before the sample it names, streamed or the file whole; and
    # without the event the second life cannot be told, and verify fails (the event is what it reads)
    from hil.nodes.fusion import realigned_first_received, realigned_imu_seq
    from hil.record.rerun import RERUN_WINDOW_S, rerun_fusion_records

    records = list(read_session(out).records)
    (event,) = [r for r in records if r.topic.endswith("/event/fusion") and r.decode().kind == "realigned"]  # type: ignore[attr-defined]
    imu_seq = realigned_imu_seq(event.decode().detail)  # type: ignore[attr-defined]
    assert imu_seq is not None
    # ... the event naming the first input of each stream the new process received (rerun's
    # inputs for it), the IMU sample among them
    firsts = realigned_first_received(event.decode().detail)  # type: ignore[attr-defined]
    assert firsts is not None and imu_seq in firsts.values(), event.decode().detail  # type: ignore[attr-defined]
    moved = _with_event_before_sample(records, event, imu_seq)
    for window_ns in (round(RERUN_WINDOW_S * 1e9), None):
        again = rerun_fusion_records(moved, window_ns=window_ns, worker=False)
        assert (again.difference, again.restarts) == (None, 1), window_ns
        assert again.n_recorded > 1000
    blind = rerun_fusion_records([r for r in records if r is not event], window_ns=None, worker=False)
    assert blind.difference is not None and blind.restarts == 0
    assert "restarted process(es) more than the recording has realigned events for" in blind.difference
    # ... and without the sample it names, verify says the restarted fusion cannot be told (a loss
    # of its inputs otherwise excused every output)
    lacking = [r for r in records if not (r.topic.endswith("/synced/imu") and r.decode().seq == imu_seq)]  # type: ignore[attr-defined]
    res = rerun_fusion_records(lacking, window_ns=None, worker=False)
    assert res.difference is not None and f"restarted at imu seq {imu_seq}" in res.difference
