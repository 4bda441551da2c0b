"""``hil rerun`` streams a recording: bounded memory, the same verdict as reading the file whole.

A one-hour session is ~12 million messages; ``read_session`` would hold them all (several GB of
Python objects). The rerun instead holds a window of rig time (inputs waiting for their place in
the total order, outputs waiting for their counterpart). These tests check that streaming gives
exactly what the whole-file rerun gives -- on the golden recording with windows small enough
that inputs are released long before the end, on a recording whose order defeats the window
(it falls back and says so), and on a tampered recording (the same first difference is named);
and that the fusion in a worker process (``worker=True``) recomputes what one process does.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import pytest

from hil.messages import TYPES_BY_NAME
from hil.record import rerun as rerun_module
from hil.record import rerun_timesync as rerun_timesync_module
from hil.record.matching import SeqSet
from hil.record.mcapio import Record, SessionStream, SessionWriter, read_session
from hil.record.rerun import rerun, rerun_fusion, rerun_fusion_file, rerun_fusion_records
from hil.record.rerun_timesync import rerun_timesync, rerun_timesync_records
from hil.runners.sim_worker import LocalNode, RemoteNode, WorkerError
from tests.replay.helpers import GOLDEN


def _rewrite(dst: Path, payload_of: Callable[[Record], bytes]) -> None:
    """The golden recording written again, each record's payload as ``payload_of`` gives it."""
    s = read_session(GOLDEN)
    w = SessionWriter(dst)
    for r in s.records:
        w.write(
            r.topic,
            TYPES_BY_NAME[r.schema],
            payload_of(r),
            log_time_ns=r.log_time_ns,
            publish_time_ns=r.publish_time_ns,
            seq=r.sequence,
        )
    w.close()


def _copy(dst: Path, tamper: dict[tuple[str, int], dict[str, object]]) -> None:
    """Rewrite the golden recording, changing fields of the (topic suffix, seq) records named."""

    def payload_of(r: Record) -> bytes:
        payload = r.payload
        for (suffix, seq), fields in tamper.items():
            if r.topic.endswith(suffix) and r.sequence == seq:
                d = msgspec.json.decode(payload)
                d.update(fields)
                payload = msgspec.json.encode(d)
        return payload

    _rewrite(dst, payload_of)


def test_seqset_holds_dense_and_odd_seqs() -> None:
    s = SeqSet()
    for seq in (0, 7, 8, 1_000_003, -1, 1 << 40):
        s.add("imu", seq)
    assert ("imu", 7) in s and ("imu", 1_000_003) in s and ("imu", -1) in s and ("imu", 1 << 40) in s
    assert ("imu", 6) not in s and ("gnss", 7) not in s and ("imu", 2_000_000) not in s


def test_streaming_with_a_short_window_equals_the_whole_file_rerun() -> None:
    whole = rerun_fusion(read_session(GOLDEN))
    assert whole.difference is None and whole.n_recorded > 1000
    # the golden file is 4 s; time sync holds the IMU until its tag filter locks (3 tags, at most
    # 3.5 s: hil.timesync.core hold_until_locked_ns), so the first synced IMU is recorded 3 s after
    # its stamp. A window just past that hold still releases the inputs all along the file.
    for window_s in (3.75,):
        res, stream, note = rerun_fusion_file(GOLDEN, window_s=window_s)
        assert note == "", note
        assert not stream.truncated
        assert (res.inputs_used, res.n_recomputed, res.n_recorded) == (
            whole.inputs_used,
            len(whole.recomputed),
            whole.n_recorded,
        )
        assert res.difference is None


def test_a_recording_out_of_order_beyond_the_window_is_rerun_whole_and_says_so() -> None:
    res, _stream, note = rerun_fusion_file(GOLDEN, window_s=0.0)
    assert "reran with the whole file in memory" in note, note
    assert res.difference is None and res.inputs_used == rerun_fusion(read_session(GOLDEN)).inputs_used


def test_streaming_names_the_same_first_difference_as_the_whole_file(tmp_path: Path) -> None:
    bad = tmp_path / "tampered.mcap"
    _copy(
        bad, {("/nav/ins", 40): {"pos_ned_m": [1.0, 2.0, 3.0]}, ("/nav/ins", 90): {"vel_ned_mps": [0.0] * 3}}
    )
    whole = rerun_fusion(read_session(bad)).difference
    assert whole is not None and whole.startswith("nav/ins seq 40: field 'pos_ned_m' differs")
    res, _s, note = rerun_fusion_file(bad, window_s=3.75)
    assert note == "" and res.difference == whole
    rc, lines = rerun(str(bad), verify=True)  # the CLI's default window
    assert rc == 1 and lines[-1] == f"VERIFY FAILED: {whole}"


def _legacy_nav_copy(dst: Path, tamper_ins_seq: int | None = None) -> int:
    """The golden with every solution in NavSolution's previous form (an absent sigma ``null``,
    not ``[]``); ``tamper_ins_seq``: that one of nav/ins also moved. Returns how many changed form."""
    changed = 0

    def payload_of(r: Record) -> bytes:
        nonlocal changed
        if "/nav/" not in r.topic:
            return r.payload
        d = msgspec.json.decode(r.payload)
        for k in ("pos_sigma_m", "vel_sigma_mps"):  # the previous form's two (_NavSolutionV0)
            if d.get(k) == []:
                d[k] = None
        if r.topic.endswith("/nav/ins") and r.sequence == tamper_ins_seq:
            d["pos_ned_m"] = [1.0, 2.0, 3.0]
        new = msgspec.json.encode(d)
        changed += new != r.payload
        return new

    _rewrite(dst, payload_of)
    return changed


def test_solutions_recorded_in_the_previous_form_verify_and_a_change_among_them_is_named(
    tmp_path: Path,
) -> None:
    """The rerun compares recorded bytes first and brings a recorded solution to today's form only
    where they differ: a recording of the previous form still verifies bit for bit, and a real
    change in it is named by its field, not by the form."""
    legacy = tmp_path / "legacy_form.mcap"
    assert _legacy_nav_copy(legacy) > 100
    rc, lines = rerun(str(legacy), verify=True)
    assert rc == 0 and "VERIFY OK" in lines[-1], lines
    bad = tmp_path / "legacy_form_tampered.mcap"
    _legacy_nav_copy(bad, tamper_ins_seq=40)
    rc, lines = rerun(str(bad), verify=True)
    assert rc == 1 and lines[-1].startswith("VERIFY FAILED: nav/ins seq 40: field 'pos_ned_m' differs"), lines


def test_timesync_streaming_names_a_changed_restamp_and_passes_the_original(tmp_path: Path) -> None:
    assert rerun_timesync(read_session(GOLDEN)).difference is None
    assert rerun_timesync_records(SessionStream(GOLDEN)).difference is None
    bad = tmp_path / "tampered_ts.mcap"
    _copy(bad, {("/synced/imu", 300): {"stamp_ns": 1}})
    diff = rerun_timesync_records(SessionStream(bad)).difference
    assert diff is not None and diff.startswith("synced/imu seq 300: field 'stamp_ns' differs"), diff
    rc, lines = rerun(str(bad), core="timesync", verify=True)
    assert rc == 1 and "synced/imu seq 300" in lines[-1]


def _timesync_batches_seen(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The sizes of the batches the time-sync rerun hands its worker (the worker path, observed)."""
    sizes: list[int] = []
    call = RemoteNode.call

    def counted(self: RemoteNode, fn: Any, *args: Any) -> None:
        if fn is rerun_timesync_module.restamps:
            sizes.append(len(args[0]))
        call(self, fn, *args)

    monkeypatch.setattr(RemoteNode, "call", counted)
    monkeypatch.setattr(rerun_timesync_module, "NODE_BATCH", 100)  # the golden's 4 s: many batches
    return sizes


def test_the_time_sync_in_a_worker_matches_what_one_process_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    alone = rerun_timesync_records(SessionStream(GOLDEN), worker=False)
    sizes = _timesync_batches_seen(monkeypatch)
    forked = rerun_timesync_records(SessionStream(GOLDEN), worker=True)
    assert len(sizes) > 10 and sum(sizes) == forked.measurements + forked.timetags, sizes
    assert alone == forked and forked.difference is None and forked.n_recorded > 1000
    # a changed re-stamp and one recorded too late are named alike (the matcher's operations
    # run in file order, however far behind the worker is)
    bad = tmp_path / "tampered_ts.mcap"
    _copy(bad, {("/synced/imu", 300): {"stamp_ns": 1}, ("/synced/imu", 900): {"stamp_ns": 2}})
    alone = rerun_timesync_records(SessionStream(bad), worker=False)
    forked = rerun_timesync_records(SessionStream(bad), worker=True)
    assert alone == forked and (forked.difference or "").startswith("synced/imu seq 300: field 'stamp_ns'")


def test_a_malformed_measurement_fails_the_time_sync_rerun_as_in_one_process(tmp_path: Path) -> None:
    bad = tmp_path / "malformed_ts.mcap"

    def payload_of(r: Record) -> bytes:
        return b'{"seq": "nine"}' if r.topic.endswith("/sensor/imu") and r.sequence == 200 else r.payload

    _rewrite(bad, payload_of)
    errors = []
    for worker in (False, True):
        with pytest.raises(msgspec.ValidationError) as err:
            rerun_timesync_records(SessionStream(bad), worker=worker)
        errors.append(str(err.value))
    assert errors[0] == errors[1] and "seq" in errors[0], errors


def test_progress_is_reported_in_bytes_of_the_file() -> None:
    seen: list[tuple[int, int]] = []
    rc, _lines = rerun(str(GOLDEN), verify=True, on_progress=lambda done, total: seen.append((done, total)))
    assert rc == 0 and seen
    size = GOLDEN.stat().st_size
    assert all(0 < d <= t == size for d, t in seen)


def _batches_seen(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The sizes of the input batches the rerun hands its worker (the worker path, observed)."""
    sizes: list[int] = []
    send = RemoteNode.replay

    def replay(self: RemoteNode, inputs: list[Any], keep: bool, only: Any = None, **relay: Any) -> None:
        sizes.append(len(inputs))
        send(self, inputs, keep, only, **relay)

    monkeypatch.setattr(RemoteNode, "replay", replay)
    monkeypatch.setattr(rerun_module, "REPLAY_BATCH", 100)  # the golden's 4 s: several batches
    return sizes


def test_the_fusion_in_a_worker_recomputes_what_one_process_does(monkeypatch: pytest.MonkeyPatch) -> None:
    records = read_session(GOLDEN).records
    alone = rerun_fusion_records(records, window_ns=None, keep_outputs=True, worker=False)
    sizes = _batches_seen(monkeypatch)
    forked = rerun_fusion_records(records, window_ns=None, keep_outputs=True, worker=True, split=False)
    assert len(sizes) > 3 and sum(sizes) == forked.inputs_used, sizes
    assert forked.difference is None and alone.difference is None
    assert forked.recomputed == alone.recomputed and len(alone.recomputed) > 1000
    assert (forked.n_recorded, forked.n_recomputed, forked.inputs_used, forked.inputs_dropped) == (
        alone.n_recorded,
        alone.n_recomputed,
        alone.inputs_used,
        alone.inputs_dropped,
    )
    # streamed, and streamed past a window the order defeats (a second pass, a second worker)
    res, _s, note = rerun_fusion_file(GOLDEN, window_s=3.75, worker=True, split=False)
    assert note == "" and res.difference is None and res.n_recomputed == alone.n_recomputed
    res, _s, note = rerun_fusion_file(GOLDEN, window_s=0.0, worker=True, split=False)
    assert "reran with the whole file in memory" in note and res.difference is None


def test_the_worker_names_the_same_first_difference(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bad = tmp_path / "tampered.mcap"
    _copy(bad, {("/nav/ekf15", 300): {"vel_ned_mps": [0.0] * 3}, ("/nav/ins", 90): {"pos_ned_m": [0.0] * 3}})
    alone, _s, _n = rerun_fusion_file(bad, window_s=3.75, worker=False)
    sizes = _batches_seen(monkeypatch)
    forked, _s, _n = rerun_fusion_file(bad, window_s=3.75, worker=True, split=False)
    assert sizes and alone.difference is not None
    assert forked.difference == alone.difference and forked.difference.startswith("nav/ins seq 90")
    shared, _s, _n = rerun_fusion_file(bad, window_s=3.75, worker=True, split=True, here=False)  # two workers
    assert shared.difference == alone.difference
    here, _s, _n = rerun_fusion_file(bad, window_s=3.75, worker=True, split=True, here=True)  # one and this
    assert here.difference == alone.difference


def test_a_worker_that_dies_fails_the_rerun_and_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    send = RemoteNode.replay

    def replay_then_die(
        self: RemoteNode, inputs: list[Any], keep: bool, only: Any = None, **relay: Any
    ) -> None:
        os.kill(self.pid, signal.SIGKILL)
        send(self, inputs, keep, only, **relay)

    monkeypatch.setattr(RemoteNode, "replay", replay_then_die)
    with pytest.raises(WorkerError, match="worker process died"):
        rerun_fusion_records(read_session(GOLDEN).records, window_ns=None, worker=True, split=False)
    with pytest.raises(WorkerError, match="worker process died"):  # either of two
        rerun_fusion_records(
            read_session(GOLDEN).records, window_ns=None, worker=True, split=True, here=False
        )
    with pytest.raises(WorkerError, match="worker process died"):  # the one beside this process's share
        rerun_fusion_records(read_session(GOLDEN).records, window_ns=None, worker=True, split=True, here=True)


def _recomputes_as(res: Any, alone: Any) -> None:
    """A shared rerun's verdict is one process's: no difference, the same solutions and counts."""
    assert res.difference is None and res.recomputed == alone.recomputed and len(alone.recomputed) > 1000
    assert (res.n_recorded, res.n_recomputed, res.inputs_used) == (
        alone.n_recorded,
        alone.n_recomputed,
        alone.inputs_used,
    )


def test_two_workers_sharing_the_estimators_recompute_what_one_process_does(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each worker runs the whole core with its share of the estimators, the first with the GNSS
    gate's reference (whose verdicts decide for all), the second taking its verdicts one batch
    later: merged into one core's order, the same solutions, the same count, every one compared."""
    records = read_session(GOLDEN).records
    alone = rerun_fusion_records(records, window_ns=None, keep_outputs=True, worker=False)
    shares: list[Any] = []
    relays: list[Any] = []
    send = RemoteNode.replay

    def replay(self: RemoteNode, inputs: list[Any], keep: bool, only: Any = None, **relay: Any) -> None:
        shares.append(only)
        relays.append(relay)
        send(self, inputs, keep, only, **relay)

    monkeypatch.setattr(RemoteNode, "replay", replay)
    monkeypatch.setattr(rerun_module, "REPLAY_BATCH", 100)
    shared = rerun_fusion_records(
        records, window_ns=None, keep_outputs=True, worker=True, split=True, here=False
    )
    _recomputes_as(shared, alone)
    a = shares[0]
    b = next(s for s in shares if s != a)
    assert len(shares) > 6 and set(shares) == {a, b} and shares.count(a) == shares.count(b)
    assert a | b == {"ins", "comp1", "comp3f", "compvs", "cf3", "kfvel", "ekf15"} and not a & b
    assert "ekf15" in a  # the reference, in one share only
    # the first keeps the gate's verdicts on each batch, the second takes them with that batch
    assert all(r == {"verdicts": True} for o, r in zip(shares, relays, strict=True) if o == a)
    to_b = [r["relay"] for o, r in zip(shares, relays, strict=True) if o == b]
    assert all(isinstance(v, dict) for v in to_b) and sum(len(v) for v in to_b) > 0


def test_a_worker_and_this_process_sharing_the_estimators_recompute_what_one_process_does(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On two CPUs the second share runs in the process that reads and compares (``LocalNode``):
    the worker one batch ahead with the gate's reference, this process taking each batch with its
    verdicts once the worker has run it. The same solutions, in one core's order, as one process."""
    records = read_session(GOLDEN).records
    alone = rerun_fusion_records(records, window_ns=None, keep_outputs=True, worker=False)
    calls: list[tuple[str, Any, Any, int]] = []
    send, keep = RemoteNode.replay, LocalNode.replay

    def remote(self: RemoteNode, inputs: list[Any], keep_: bool, only: Any = None, **relay: Any) -> None:
        calls.append(("worker", only, relay, len(inputs)))
        send(self, inputs, keep_, only, **relay)

    def local(self: LocalNode, inputs: list[Any], keep_: bool, only: Any = None, **relay: Any) -> None:
        calls.append(("here", only, relay, len(inputs)))
        keep(self, inputs, keep_, only, **relay)

    monkeypatch.setattr(RemoteNode, "replay", remote)
    monkeypatch.setattr(LocalNode, "replay", local)
    monkeypatch.setattr(rerun_module, "REPLAY_BATCH_HERE", 100)
    here = rerun_fusion_records(
        records, window_ns=None, keep_outputs=True, worker=True, split=True, here=True
    )
    _recomputes_as(here, alone)
    worker = [c for c in calls if c[0] == "worker"]
    mine = [c for c in calls if c[0] == "here"]
    assert len(worker) > 6 and len(mine) == len(worker)
    assert {c[1] for c in worker} == {frozenset({"ins", "comp3f", "compvs", "cf3", "ekf15"})}
    assert {c[1] for c in mine} == {frozenset({"comp1", "kfvel"})}  # the two lightest
    assert all(c[2] == {"verdicts": True} for c in worker)
    # this process runs batch N after the worker was sent N + 1, with the verdicts of N
    assert [c[3] for c in mine] == [c[3] for c in worker] and calls[0][0] == calls[1][0] == "worker"
    assert sum(c[3] for c in worker) == here.inputs_used
    assert all(isinstance(c[2]["relay"], dict) for c in mine) and sum(len(c[2]["relay"]) for c in mine) > 0


@pytest.mark.parametrize("heavy", [True, False])
def test_on_two_cpus_this_process_takes_a_share_of_a_heavy_configuration_only(
    monkeypatch: pytest.MonkeyPatch, heavy: bool
) -> None:
    """Two CPUs (a worker possible, a second one not): a consumer IMU's configuration (filters in
    feedback form, ekf15's calibration states) shares its estimators with the reading process;
    a tactical one keeps one worker for all, since its reading outweighs what it would move."""
    from dataclasses import replace

    from hil.fusion.core import FusionConfig
    from hil.record.rerun import share_here_pays

    cfg = FusionConfig(estimators=("comp1", "comp3f", "compvs", "cf3", "kfvel", "ekf15"))
    assert not share_here_pays(cfg)
    assert share_here_pays(replace(cfg, feedback=("comp1",))) and share_here_pays(
        replace(cfg, ekf_calibration="gyro")
    )
    monkeypatch.setattr(rerun_module, "worker_possible", lambda cpus=2: cpus <= 2)
    monkeypatch.setattr(rerun_module, "worker_pays", lambda node: True)
    monkeypatch.setattr(rerun_module, "share_here_pays", lambda cfg: heavy)
    made: list[str] = []
    init = LocalNode.__init__

    def counted(self: LocalNode, node: Any) -> None:
        made.append(node.name)
        init(self, node)

    monkeypatch.setattr(LocalNode, "__init__", counted)
    res = rerun_fusion_records(read_session(GOLDEN).records, window_ns=None)
    assert res.difference is None and res.n_recomputed > 1000
    assert len(made) == (1 if heavy else 0)


def test_the_first_share_holds_the_gate_reference_and_the_rest_is_balanced() -> None:
    from dataclasses import replace

    from hil.fusion.core import FusionConfig
    from hil.record.rerun import split_estimators

    cfg = FusionConfig(estimators=("comp1", "comp3f", "compvs", "cf3", "kfvel", "ekf15"))
    a, b = split_estimators(cfg) or ((), ())
    assert "ekf15" in a and "ekf15" not in b
    assert sorted({*a, *b}) == sorted(cfg.estimators) and not set(a) & set(b)
    assert (len(a), len(b)) == (3, 3) and "kfvel" in a  # ekf15 4 + kfvel 2 + one of 3, against 3 x 3
    order = list(cfg.estimators)
    assert [order.index(e) for e in a] == sorted(order.index(e) for e in a)  # the configuration's order
    assert [order.index(e) for e in b] == sorted(order.index(e) for e in b)
    # no reference among the estimators: each decides for itself, nothing is shared
    a, b = split_estimators(replace(cfg, estimators=("comp1", "comp3f", "compvs", "cf3"))) or ((), ())
    assert sorted({*a, *b}) == ["cf3", "comp1", "comp3f", "compvs"] and not set(a) & set(b)
    # too few to share, or the horizon's outputs (not one solution per estimator per output)
    assert split_estimators(replace(cfg, estimators=("comp1", "cf3", "ekf15"))) is None
    four = split_estimators(replace(cfg, estimators=("ekf15", "comp1", "cf3", "compvs")))
    assert four == (("ekf15", "compvs"), ("comp1", "cf3"))
    assert split_estimators(replace(cfg, output_predictor=False)) is None
    # this process's share, beside its reading: the two lightest, never the reference
    assert split_estimators(cfg, here=True) == (("comp3f", "compvs", "cf3", "ekf15"), ("comp1", "kfvel"))
    assert split_estimators(replace(cfg, estimators=("ekf15", "kfvel", "cf3", "comp1")), here=True) == (
        ("ekf15", "comp1"),
        ("kfvel", "cf3"),
    )
    assert split_estimators(replace(cfg, estimators=("comp1", "cf3", "ekf15")), here=True) is None


def test_hil_rerun_workers_option() -> None:
    from tests.conftest import run_hil

    proc = run_hil("rerun", str(GOLDEN), "--verify", "--workers", "2", timeout=300)
    assert proc.returncode == 0 and "VERIFY OK" in proc.stdout, proc.stdout + proc.stderr
    proc = run_hil("rerun", str(GOLDEN), "--verify", "--share-here", timeout=300)
    assert proc.returncode == 0 and "VERIFY OK" in proc.stdout, proc.stdout + proc.stderr
    for bad in (
        ["--one-process", "--workers", "2"],
        ["--one-process", "--share-here"],
        ["--workers", "1", "--share-here"],
    ):
        proc = run_hil("rerun", str(GOLDEN), *bad, timeout=120)
        assert proc.returncode == 2 and "choose one" in proc.stderr and "Traceback" not in proc.stderr, (
            bad,
            proc.stderr,
        )
