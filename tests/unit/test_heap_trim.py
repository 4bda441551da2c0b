"""Heap trimming gives a thread arena's free pages back, and every service reports it in status
(and a status that could not go out in the next one)."""

from __future__ import annotations

import gc
import subprocess
import sys
import threading
import time

import pytest

from hil.bus.pubsub import Stats, Subscriber
from hil.bus.session import BusConfig, open_session
from hil.messages import ServiceStatus
from hil.runtime import heap
from hil.runtime.heap import OFFLINE_GEN0_THRESHOLD, HeapTrimmer, rss_kib
from hil.runtime.service import HEAP_TRIM_PERIOD_S, Service, ServiceContext, heap_trim_period

# In a child, so the pytest process's heap is not the one measured: a worker thread (its own
# glibc arena, as Zenoh's threads have) makes 120 MB of > 512 B objects -- malloc's, not
# pymalloc's -- and keeps every 50th, which pins the arena's top; then one trim.
_FRAGMENT = """
import json, os, threading
from hil.runtime import heap
from hil.runtime.heap import OFFLINE_GEN0_THRESHOLD, HeapTrimmer, rss_kib
keep = []
def work():
    objs = [bytes(600) + os.urandom(8) for _ in range(200_000)]
    keep.extend(objs[::50])
t = threading.Thread(target=work); t.start(); t.join()
before = rss_kib()
h = HeapTrimmer()
released = h.trim()
print(json.dumps({"before": before, "after": rss_kib(), "released": released, **h.counters()}))
"""


def test_trim_gives_back_a_fragmented_thread_arena() -> None:
    import json

    out = subprocess.run([sys.executable, "-c", _FRAGMENT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    assert HeapTrimmer().available  # glibc: this machine and the images
    # ~4,000 objects still alive (2.4 MB); the other ~117 MB were free but resident
    assert r["before"] - r["after"] > 60 * 1024
    assert r["released"] == r["heap_trim_released_kib"] > 60 * 1024
    assert r["heap_trims"] == 1 and r["heap_trim_max_us"] > 0


def test_rss_is_this_process() -> None:
    with open("/proc/self/status") as fh:
        vm = next(int(line.split()[1]) for line in fh if line.startswith("VmRSS:"))
    assert abs((rss_kib() or 0) - vm) < 8 * 1024


@pytest.mark.parametrize(
    ("value", "period", "bad"),
    [
        (2.5, 2.5, False),
        (0, 0.0, False),
        (-1, HEAP_TRIM_PERIOD_S, True),
        ("soon", HEAP_TRIM_PERIOD_S, True),
        (True, HEAP_TRIM_PERIOD_S, True),
        (float("nan"), HEAP_TRIM_PERIOD_S, True),
    ],
)
def test_trim_period_option(value: object, period: float, bad: bool) -> None:
    got, problem = heap_trim_period({"heap_trim_s": value})
    assert got == period
    assert (problem is not None) == bad
    if bad:
        assert "heap_trim_s" in problem and "trimming every 10 s" in problem  # type: ignore[operator]
    assert heap_trim_period({}) == (HEAP_TRIM_PERIOD_S, None)


def test_trim_period_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HIL_HEAP_TRIM_S", "0")
    assert heap_trim_period({}, 1.0) == (0.0, None)
    assert heap_trim_period({"heap_trim_s": 5}, 1.0) == (5.0, None)  # the option wins
    monkeypatch.setenv("HIL_HEAP_TRIM_S", "never")
    got, problem = heap_trim_period({}, 1.0)
    assert got == 1.0 and problem is not None and problem.startswith("HIL_HEAP_TRIM_S='never'")
    monkeypatch.setenv("HIL_HEAP_TRIM_S", " ")
    assert heap_trim_period({}, 1.0) == (1.0, None)


class _Idle(Service):
    name = "idle"

    def needs_run(self) -> bool:
        return False


class _IdleTrimmingEverySecond(_Idle):
    heap_trim_default_s = 1.0  # as the recorder


def _statuses(
    options: dict[str, object], rig: str, seconds: float, cls: type[_Idle] = _Idle
) -> list[ServiceStatus]:
    from hil.bus.keys import Keys

    got: list[ServiceStatus] = []
    probe = open_session(BusConfig.from_env())
    sub = Subscriber(probe, Keys(rig).status("idle"), ServiceStatus, lambda m, _k: got.append(m), Stats())
    ctx = ServiceContext(name="idle", rig=rig, session=open_session(BusConfig.from_env()), options=options)
    svc = cls(ctx)
    thread = threading.Thread(target=svc.start, daemon=True)
    thread.start()
    time.sleep(seconds)
    ctx.stop.set()
    thread.join(timeout=5)
    ctx.session.close()
    del sub
    probe.close()
    return got


class _IdleWithABadFirstCounter(_Idle):
    """Its first status cannot be built (a counter that is no integer): that status is lost."""

    calls = 0

    def extra_status(self) -> dict[str, int]:
        self.calls += 1
        return {"bad": float("nan")} if self.calls == 1 else {}  # type: ignore[dict-item]


def test_a_status_that_cannot_go_out_is_counted_in_the_next(zenoh_hub: str) -> None:
    # a lost status leaves a gap in its seqs in the recording: the next status says where and why
    got = _statuses({}, "t-status-lost", 2.5, _IdleWithABadFirstCounter)
    assert got and got[0].seq == 1, [m.seq for m in got]  # seq 0 was spent on the lost one
    last = got[-1].counter_map()
    assert last["errors.status_publish"] == 1 and "bad" not in last
    assert got[-1].last_error.startswith("status seq 0: ValueError"), got[-1].last_error


def test_service_trims_on_schedule_and_reports(zenoh_hub: str) -> None:
    got = _statuses({"heap_trim_s": 1}, "t-heap-1", 3.6)
    assert len(got) >= 3
    last = got[-1].counter_map()
    assert last["heap_trims"] >= 2  # at ~1 s, ~2 s, ~3 s
    assert last["rss_kib"] > 10 * 1024 and "heap_trim_released_kib" in last
    assert "errors.options" not in last


def test_service_counts_a_bad_trim_option_and_keeps_running(zenoh_hub: str) -> None:
    got = _statuses({"heap_trim_s": "often"}, "t-heap-2", 1.5)
    assert got and got[-1].counter_map()["errors.options"] == 1
    assert "heap_trim_s='often'" in got[-1].last_error
    assert got[-1].counter_map()["heap_trims"] == 0  # default 10 s: none yet
    # 0 turns it off even where the class default would trim every second
    on = _statuses({}, "t-heap-3", 2.5, _IdleTrimmingEverySecond)
    assert on and on[-1].counter_map()["heap_trims"] >= 1
    off = _statuses({"heap_trim_s": 0}, "t-heap-4", 2.5, _IdleTrimmingEverySecond)
    assert off and off[-1].counter_map()["heap_trims"] == 0


# In a child, so the pytest process's collector is not the one frozen: start-up objects (a live
# one, numba's kernels) leave the collector's reach, start-up garbage in a cycle is collected
# first, and what the run makes afterwards is tracked as before.
_FREEZE = """
import gc, json, weakref
from hil.runtime import jit
class Node: pass
live = Node(); live.me = live
junk = Node(); junk.me = junk; junk_ref = weakref.ref(junk); del junk
tracked_before = len(gc.get_objects())
how = jit.enable_for_run()
after = Node()
ids = {id(o) for o in gc.get_objects()}
print(json.dumps({"how": how, "junk_alive": junk_ref() is not None, "live_tracked": id(live) in ids,
                  "after_tracked": id(after) in ids, "frozen": gc.get_freeze_count(),
                  "tracked_before": tracked_before, "tracked": len(ids), "gen0": gc.get_threshold()[0]}))
"""


def test_a_run_freezes_its_start_up_out_of_the_collectors_reach() -> None:
    import json

    proc = subprocess.run([sys.executable, "-c", _FREEZE], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert not got["junk_alive"]  # collected before the freeze, not frozen as garbage
    assert not got["live_tracked"]
    assert got["after_tracked"]
    # numba's objects (when it loads) join the modules': a full collection walks a few thousand
    assert got["frozen"] > got["tracked_before"] > got["tracked"]
    assert got["gen0"] == OFFLINE_GEN0_THRESHOLD  # young collections as rare as a window's end


def test_a_caller_of_the_offline_runs_keeps_its_collector(monkeypatch: pytest.MonkeyPatch) -> None:
    """Only hil's own process freezes and retunes its collector: a test or a notebook that runs
    ``hil sim`` or a rerun as a function keeps Python's (frozen objects in a cycle never go)."""
    monkeypatch.setattr(heap, "command_process", False)
    threshold, frozen = gc.get_threshold(), gc.get_freeze_count()
    heap.freeze_command_startup()
    assert gc.get_threshold() == threshold and gc.get_freeze_count() == frozen
