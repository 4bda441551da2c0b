"""Where a live rig's CPU goes beside the work: how often its threads block and are woken.

``hil up``'s CPU table and ``hil bench rig`` count each service's wake-ups (voluntary context
switches of every thread, from /proc); on a VM each costs tens of µs of CPU."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

from hil.bench.rig import _cpu_of, wakeup_cost_us
from hil.runtime.supervisor import Usage, proc_usage, proc_wakeups


def test_a_process_wake_ups_count_every_thread_and_its_children() -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", "import time\nfor _ in range(400): time.sleep(0.001)\ninput()"],
        stdin=subprocess.PIPE,
        text=True,
    )
    try:
        before = proc_wakeups(os.getpid(), tree=False)
        assert before is not None
        done, counted, release = threading.Event(), threading.Event(), threading.Event()

        def sleeper() -> None:  # a thread of this process that blocks 50 times, then waits
            for _ in range(50):
                done.wait(0.001)
            counted.set()
            release.wait(60)

        t = threading.Thread(target=sleeper)
        t.start()
        try:
            assert counted.wait(60)
            after = proc_wakeups(os.getpid(), tree=False)  # (a thread that ended is not counted)
        finally:
            release.set()
            t.join(timeout=60)
        assert after is not None and after - before >= 50
        # the child's 400 sleeps show in the tree's count, not in the process's own
        polls = 0
        while (proc_wakeups(os.getpid()) or 0) - (proc_wakeups(os.getpid(), tree=False) or 0) < 400:
            polls += 1
            assert polls < 1200, "the child's sleeps never showed in the tree's count (60 s)"
            done.wait(0.05)
    finally:
        try:
            child.communicate("\n", timeout=60)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
    assert proc_wakeups(2**22 + 7) is None  # no such process


def test_a_services_usage_adds_its_lives_and_never_goes_negative() -> None:
    # a restarted service: its first life from time zero to its death, its second from its start
    base, died = Usage(1.5, 300), Usage(4.0, 1300)
    second = Usage(0.8, 200).since(Usage())
    assert died.since(base) + second == Usage(3.3, 1200)
    # a successor's count starts again at 0: measured against the old base it is nothing, not
    # negative (the table once showed "fusion -0.93 s")
    assert Usage(0.2, 10).since(base) == Usage(0.0, 0)
    mine = proc_usage(os.getpid())
    assert mine is not None and mine.cpu_s > 0 and mine.wakeups > 0
    assert proc_usage(2**22 + 7) is None  # no such process


def test_the_cpu_table_is_read_with_and_without_its_wake_ups_column() -> None:
    new = (
        "CPU over 30.0 s of wall time (share of one core; wake-ups: its threads' a second):\n"
        "  fusion            2.77 s     9.2 %      458 wake-ups/s\n"
        "  all               3.00 s    10.0 %      500 wake-ups/s\n"
    )
    old = "CPU over 30.0 s of wall time (share of one core):\n  fusion            2.77 s     9.2 %\n"
    assert _cpu_of(new) == (30.0, {"fusion": 2.77})
    assert _cpu_of(old) == (30.0, {"fusion": 2.77})


def test_measuring_the_wake_up_cost_leaves_no_thread_behind() -> None:
    sleep_us, _handoff_us = wakeup_cost_us(n=50)
    assert sleep_us > 0.0  # (a hand-over's extra is clamped at 0: nothing to assert of it alone)
    assert not [t for t in threading.enumerate() if t.name == "wakeup-cost"]
