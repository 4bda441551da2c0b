"""Foxglove's well-known types in the recordings hil writes: the conversion (frames, quaternions,
covariance, logs) and a fresh ``hil sim`` recording read by the MCAP project's protobuf decoder
with the schemas the file embeds (tests/wellknown_reader.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hil.messages import Event, NavSolution, RunInfo, ServiceStatus, Truth, decode
from hil.nav.attitude import euler_to_quat, quat_to_dcm
from hil.record.mcapio import read_session
from hil.wellknown import SCHEMAS, WellKnown, q_enu_flu, yaw_rad
from tests.wellknown_reader import decode_wellknown

ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FRD_FROM_FLU = np.diag([1.0, -1.0, -1.0])


def test_the_body_attitude_in_enu_is_the_ned_attitude_turned_by_both_frame_changes() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        euler = [rng.uniform(-math.pi, math.pi), rng.uniform(-1.5, 1.5), rng.uniform(-math.pi, math.pi)]
        q_nb = euler_to_quat(euler)
        want = ENU_FROM_NED @ quat_to_dcm(q_nb) @ FRD_FROM_FLU  # FLU body -> ENU
        assert np.allclose(quat_to_dcm(np.array(q_enu_flu(list(q_nb)))), want, atol=1e-12)
        assert math.isclose(yaw_rad(list(q_nb)), euler[2] % (2 * math.pi), abs_tol=1e-9)
    # heading north, level: the body's x (forward) is ENU's y (north)
    north = quat_to_dcm(np.array(q_enu_flu([1.0, 0.0, 0.0, 0.0])))
    assert np.allclose(north @ [1, 0, 0], [0, 1, 0]) and np.allclose(north @ [0, 0, 1], [0, 0, 1])


def _truth(stamp_ns: int) -> Truth:
    return Truth(
        seq=stamp_ns // 10_000_000,
        stamp_ns=stamp_ns,
        lat_deg=50.0,
        lon_deg=30.0,
        alt_m=100.0,
        pos_ned_m=[10.0, 20.0, -5.0],
        vel_ned_mps=[1.0, 2.0, 0.5],
        q_nb=[1.0, 0.0, 0.0, 0.0],
        f_b_mps2=[0.0, 0.0, -9.8],
        w_ib_b_radps=[0.0, 0.0, 0.0],
    )


def test_poses_are_decimated_on_the_rig_time_grid_and_the_bytes_are_deterministic() -> None:
    a, b = WellKnown(start_epoch_ns=10**18), WellKnown(start_epoch_ns=10**18)
    out_a = [d for t in range(0, 10**9, 10_000_000) for d in a.convert("hil/r/truth", _truth(t), 0)]
    out_b = [d for t in range(0, 10**9, 10_000_000) for d in b.convert("truth", _truth(t), 0)]
    assert out_a == out_b  # same messages, same bytes (and the key's root does not matter)
    fixes = [d for d in out_a if d.topic == "/foxglove/fix/truth"]
    assert [d.stamp_ns - 10**18 for d in fixes] == list(range(0, 10**9, 100_000_000))  # 10 Hz
    every = WellKnown(start_epoch_ns=0, pose_rate_hz=0)
    assert len([d for t in range(0, 10**8, 10_000_000) for d in every.convert("truth", _truth(t), 0)]) == 20


def test_logs_say_what_changed_in_a_status_and_every_event() -> None:
    wk = WellKnown()  # no run seen yet: dated by the caller's log time

    def status(state: str, err: str) -> ServiceStatus:
        return ServiceStatus(
            seq=0, stamp_ns=0, service="fusion", state=state, pid=1, uptime_s=1.0, last_error=err
        )

    assert wk.convert("status/fusion", status("running", ""), 5) == []
    assert wk.convert("status/fusion", status("running", ""), 6) == []
    said = wk.convert("status/fusion", status("degraded", "late input"), 7)
    assert [d.stamp_ns for d in said] == [7, 7] and all(d.topic == "/foxglove/log" for d in said)
    assert wk.convert("status/fusion", status("degraded", "late input"), 8) == []  # nothing new
    ev = Event(seq=0, stamp_ns=2_000, kind="fault_start", source="imu_emulator", detail="{}")
    assert len(wk.convert("event/imu_emulator", ev, 9)) == 1
    run = RunInfo(
        seq=0, stamp_ns=0, rig="r", start_epoch_ns=10**18, speed=1.0, scenario="s", scenario_sha256="",
        seed=1, duration_s=1.0, origin_lat_deg=0.0, origin_lon_deg=0.0, origin_alt_m=0.0,
    )  # fmt: skip
    (static,) = wk.convert("run", run, 10)
    assert static.topic == "/foxglove/tf_static" and static.stamp_ns == 10**18
    assert wk.convert("event/imu_emulator", ev, 11)[0].stamp_ns == 10**18 + 2_000  # from now on: epoch + rig


def test_every_schema_is_the_sdk_s_protobuf_schema() -> None:
    from foxglove.messages import FrameTransform, LocationFix, Log

    for cls in (LocationFix, FrameTransform, Log):
        s = cls.get_schema()
        assert SCHEMAS[s.name] == (s.name, "protobuf", bytes(s.data))


@pytest.fixture(scope="module")
def decoded(sim_recording: Path) -> dict[str, list[tuple[int, object]]]:
    return decode_wellknown(sim_recording)


def test_a_sim_recording_carries_every_well_known_channel_and_each_decodes(
    sim_recording: Path, decoded: dict[str, list[tuple[int, object]]]
) -> None:
    s = read_session(sim_recording)
    estimators = {r.topic.rsplit("/", 1)[1] for r in s.records if r.schema == "hil.NavSolution"}
    assert {"ekf15", "ins"} <= estimators
    want = {
        "/foxglove/fix/truth",
        "/foxglove/tf/truth",
        "/foxglove/fix/sensor/gnss",
        "/foxglove/tf/sensor/gnss",
    }
    want |= {f"/foxglove/{k}/nav/{e}" for e in estimators for k in ("fix", "tf")}
    want |= {"/foxglove/tf_static", "/foxglove/log"}
    assert set(decoded) == want
    assert all(decoded[t] for t in want)


def test_truth_and_estimates_are_on_the_map_and_in_the_frame_tree_where_the_messages_say(
    sim_recording: Path, decoded: dict[str, list[tuple[int, object]]]
) -> None:
    s = read_session(sim_recording)
    start = int(s.meta("hil", "start_epoch_ns"))
    truth = {m.stamp_ns: m for m in (decode(Truth, r.payload) for r in s.by_topic("hil/simrec/truth"))}
    for log_time, fix in decoded["/foxglove/fix/truth"]:
        t_ns = fix.timestamp.seconds * 10**9 + fix.timestamp.nanos - start  # type: ignore[attr-defined]
        m = truth[t_ns]
        assert log_time == start + t_ns  # the timestamp is the record's time: epoch + rig time
        assert (fix.latitude, fix.longitude, fix.altitude) == (m.lat_deg, m.lon_deg, m.alt_m)  # type: ignore[attr-defined]
        assert math.isclose(fix.heading, yaw_rad(m.q_nb))  # type: ignore[attr-defined]
        v = fix.velocity  # type: ignore[attr-defined]
        assert (v.x, v.y, v.z) == (m.vel_ned_mps[1], m.vel_ned_mps[0], -m.vel_ned_mps[2])  # ENU
    turned = [fix.heading for _t, fix in decoded["/foxglove/fix/truth"]]  # type: ignore[attr-defined]
    assert max(turned) - min(turned) > math.radians(15)  # the turn (its rate ramps up)
    tfs = decoded["/foxglove/tf/truth"]
    for _t, tf in tfs:
        m = truth[tf.timestamp.seconds * 10**9 + tf.timestamp.nanos - start]  # type: ignore[attr-defined]
        assert (tf.parent_frame_id, tf.child_frame_id) == ("enu", "truth")  # type: ignore[attr-defined]
        p = tf.translation  # type: ignore[attr-defined]
        assert (p.x, p.y, p.z) == (m.pos_ned_m[1], m.pos_ned_m[0], -m.pos_ned_m[2])
        r = tf.rotation  # type: ignore[attr-defined]
        assert np.allclose([r.w, r.x, r.y, r.z], q_enu_flu(m.q_nb))
    (_, static), *_ = decoded["/foxglove/tf_static"]
    assert (static.parent_frame_id, static.child_frame_id) == ("enu", "ned")  # type: ignore[attr-defined]
    ekf = [decode(NavSolution, r.payload) for r in s.by_topic("hil/simrec/nav/ekf15")]
    by_stamp = {m.stamp_ns: m for m in ekf}
    for _t, fix in decoded["/foxglove/fix/nav/ekf15"]:
        m = by_stamp[fix.timestamp.seconds * 10**9 + fix.timestamp.nanos - start]  # type: ignore[attr-defined]
        n, e, d = m.pos_sigma_m
        assert fix.position_covariance_type == 2  # DIAGONAL_KNOWN  # type: ignore[attr-defined]
        assert list(fix.position_covariance) == [e * e, 0, 0, 0, n * n, 0, 0, 0, d * d]  # type: ignore[attr-defined]
    ins = decoded["/foxglove/fix/nav/ins"][0][1]
    assert ins.position_covariance_type == 0  # the free INS has no covariance  # type: ignore[attr-defined]
    gnss = decoded["/foxglove/fix/sensor/gnss"][0][1]
    assert not gnss.HasField("heading") and gnss.position_covariance[0] > 0  # type: ignore[attr-defined]


def test_events_become_log_lines(decoded: dict[str, list[tuple[int, object]]]) -> None:
    lines = [m for _t, m in decoded["/foxglove/log"]]
    starts = [m for m in lines if m.message.startswith("fault_start: ")]  # type: ignore[attr-defined]
    assert len(starts) == 1 and starts[0].name == "imu_emulator" and starts[0].level == 3  # WARNING  # type: ignore[attr-defined]
    assert any(m.message.startswith("fault_end: ") for m in lines)  # type: ignore[attr-defined]
