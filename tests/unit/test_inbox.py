"""The bounded inbox every service's Zenoh callbacks feed (``hil.bus.inbox``).

GIVEN lanes per (kind, publisher) with caps per kind
WHEN one kind, or one publisher, floods
THEN only that lane loses its oldest messages (counted, handed back for a journal), the others
keep every message, the worker still takes them in arrival order, and memory stays bounded --
with real threads as the Zenoh callbacks are.
"""

from __future__ import annotations

import random
import threading

from hil.bus.inbox import AIDING_CAP, MAX_PUBLISHER_LANES, PACER_CAP, SHARED, BoundedInbox, key_kind, lane_cap


def _drain(box: BoundedInbox[tuple[str, int]]) -> list[tuple[str, int]]:
    out = []
    while (item := box.get(timeout=0)) is not None:
        out.append(item)
    return out


def test_caps_come_from_the_sensor_table_and_kinds_from_the_key() -> None:
    assert lane_cap("synced/imu") == lane_cap("sensor/imu") == PACER_CAP
    assert lane_cap("synced/gnss") == lane_cap("timetag/gnss") == AIDING_CAP
    assert lane_cap("control/fault") < PACER_CAP
    assert key_kind("synced/gnss") == "synced/gnss" and key_kind("nav/ekf15/x") == "nav/ekf15"


def test_a_flooded_kind_drops_its_own_oldest_and_the_imu_waits_behind_at_most_one_lane() -> None:
    box: BoundedInbox[tuple[str, int]] = BoundedInbox(keep_dropped=True)
    box.put("synced/imu", "tsync", ("imu", 1))
    for i in range(3 * AIDING_CAP):
        box.put("synced/gnss", "stranger", ("gnss", i))
    box.put("synced/imu", "tsync", ("imu", 2))
    got = _drain(box)
    assert got[0] == ("imu", 1) and got[-1] == ("imu", 2)  # arrival order across lanes
    junk = [n for kind, n in got if kind == "gnss"]
    assert junk == list(range(2 * AIDING_CAP, 3 * AIDING_CAP))  # the newest cap of them
    assert box.dropped == {"synced/gnss": 2 * AIDING_CAP}
    assert [n for _k, n in box.take_dropped()] == list(range(2 * AIDING_CAP))  # for the journal
    assert box.counters()["inbox.dropped.synced.gnss"] == 2 * AIDING_CAP
    assert box.peak == AIDING_CAP + 2


def test_lanes_are_per_publisher_so_a_strangers_flood_spares_the_rigs_fixes() -> None:
    box: BoundedInbox[tuple[str, int]] = BoundedInbox()
    for i in range(10):
        box.put("synced/gnss", "rig", ("rig", i))
        for j in range(AIDING_CAP):
            box.put("synced/gnss", "stranger", ("junk", i * AIDING_CAP + j))
    got = _drain(box)
    assert [n for k, n in got if k == "rig"] == list(range(10))


def test_the_number_of_lanes_is_bounded_whatever_the_publishers() -> None:
    box: BoundedInbox[tuple[str, int]] = BoundedInbox(lambda _k, _p: 4)
    for p in range(100):
        for i in range(10):
            box.put("synced/gnss", f"pub{p}", ("x", i))
    assert len(box._lanes) == MAX_PUBLISHER_LANES + 1  # the rest share one lane
    assert ("synced/gnss", SHARED) in box._lanes
    assert box.qsize() <= 4 * (MAX_PUBLISHER_LANES + 1)


def test_a_total_bound_takes_the_oldest_of_the_longest_lane() -> None:
    dropped: list[tuple[str, str, tuple[str, int]]] = []
    box: BoundedInbox[tuple[str, int]] = BoundedInbox(
        lambda _k, _p: 1000, max_total=10, on_drop=lambda k, p, item: dropped.append((k, p, item))
    )
    box.put("synced/imu", "rig", ("imu", 0))
    for i in range(20):
        box.put("synced/gnss", "stranger", ("junk", i))
    assert box.qsize() == 10
    assert all(p == "stranger" for _k, p, _i in dropped) and len(dropped) == 11
    assert _drain(box)[0] == ("imu", 0)


def test_real_threads_every_message_is_taken_or_counted_and_the_depth_stays_bounded() -> None:
    box: BoundedInbox[tuple[str, int]] = BoundedInbox(lambda kind, _p: 50 if kind == "gnss" else 10_000)
    n_junk, n_imu = 20_000, 2_000
    taken: list[tuple[str, int]] = []
    done = threading.Event()
    max_depth = [0]

    def flood() -> None:
        for i in range(n_junk):
            box.put("gnss", "stranger", ("junk", i))

    def imu() -> None:
        for i in range(n_imu):
            box.put("imu", "rig", ("imu", i))

    def worker() -> None:
        while not (done.is_set() and box.qsize() == 0):
            item = box.get(timeout=0.05)
            max_depth[0] = max(max_depth[0], box.qsize())
            if item is not None:
                taken.append(item)

    threads = [threading.Thread(target=f) for f in (flood, imu)]
    consumer = threading.Thread(target=worker)
    consumer.start()
    try:
        for t in threads:
            t.start()
    finally:
        for t in threads:
            t.join(timeout=60)
        done.set()
        consumer.join(timeout=60)
    assert not consumer.is_alive()
    imu_taken = [n for k, n in taken if k == "imu"]
    assert imu_taken == list(range(n_imu))  # every IMU message, in order: never starved
    junk_taken = sum(1 for k, _ in taken if k == "junk")
    assert junk_taken + box.dropped.get("gnss", 0) == n_junk
    assert max_depth[0] <= 10_000 + 50


def test_a_batch_is_what_get_gives_one_by_one_in_arrival_order_across_lanes() -> None:
    rng = random.Random(5)
    kinds = ["synced/imu", "sensor/gnss", "status/x", "can/vcan0"]
    one: BoundedInbox[int] = BoundedInbox()
    many: BoundedInbox[int] = BoundedInbox()
    for i in range(5000):
        kind, pub = rng.choice(kinds), rng.choice(["a", "b", "c"])
        one.put(kind, pub, i)
        many.put(kind, pub, i)
    singles = [one.get(timeout=0) for _ in range(5000)]
    batches: list[int] = []
    while chunk := many.get_many(rng.randint(1, 700), timeout=0):
        batches += chunk
    assert batches == singles == list(range(5000))  # nothing dropped under the caps: arrival order
    assert many.qsize() == 0 and many.get_many(10, timeout=0) == []
    single_lane: BoundedInbox[int] = BoundedInbox()
    for i in range(10):
        single_lane.put("synced/imu", "a", i)
    assert single_lane.get_many(4, timeout=0) == [0, 1, 2, 3] and single_lane.qsize() == 6
