"""Contract messages from the cores' arrays: one builder per message, used by the live services
and by ``hil sim`` alike, so both executors write byte-identical fields for the same values."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from hil.messages import CanFrame, ClockModel, GnssFix, ImuSample, Truth

if TYPE_CHECKING:  # python-can only for the annotation: the time-sync rerun need not import it
    import can


def truth_msg(seq: int, t_ns: int, b: Any, i: int) -> Truth:
    """``Truth`` from row ``i`` of a ``TruthBatch``."""
    import numpy as np  # here, not at the top: the time-sync rerun imports this module, never numpy

    return Truth(
        seq=seq,
        stamp_ns=t_ns,
        lat_deg=float(np.degrees(b.lat_rad[i])),
        lon_deg=float(np.degrees(b.lon_rad[i])),
        alt_m=float(b.alt_m[i]),
        pos_ned_m=b.pos_ned_m[i].tolist(),
        vel_ned_mps=b.vel_ned_mps[i].tolist(),
        q_nb=b.q_nb[i].tolist(),
        f_b_mps2=b.f_b_mps2[i].tolist(),
        w_ib_b_radps=b.w_ib_b_radps[i].tolist(),
    )


def gnss_fix_msg(seq: int, rx_ns: int, device_ns: int, b: Any, i: int) -> GnssFix:
    """A raw ``GnssFix`` (stamped at its arrival) from row ``i`` of a ``GnssBatch``."""
    import numpy as np  # as in truth_msg

    return GnssFix(
        seq=seq,
        stamp_ns=rx_ns,
        device_stamp_ns=device_ns,
        rx_stamp_ns=rx_ns,
        lat_deg=float(b.lat_deg[i]),
        lon_deg=float(b.lon_deg[i]),
        alt_m=float(b.alt_m[i]),
        pos_ned_m=np.asarray(b.pos_ned_m[i], dtype=float).tolist(),
        vel_ned_mps=np.asarray(b.vel_ned_mps[i], dtype=float).tolist(),
        pos_sigma_m=np.asarray(b.pos_sigma_m[i], dtype=float).tolist(),
        vel_sigma_mps=np.asarray(b.vel_sigma_mps[i], dtype=float).tolist(),
        fix_type=int(b.fix_type[i]),
        num_sats=int(b.num_sats[i]),
        hdop=float(b.hdop[i]),
    )


def clock_model_msg(seq: int, stamp_ns: int, m: Any) -> ClockModel:
    """``ClockModel`` from a time-sync core mapping."""
    return ClockModel(
        seq=seq,
        stamp_ns=stamp_ns,
        sensor=m.sensor,
        source=m.source,
        offset_ns=m.offset_ns,
        drift_ppb=m.drift_ppb,
        ref_device_ns=m.ref_device_ns,
        residual_rms_ns=m.residual_rms_ns,
        n_samples=m.n_samples,
        state=m.state,
        steps_detected=m.steps_detected,
    )


def can_frame_msg(seq: int, rx_ns: int, channel: str, msg: can.Message) -> CanFrame:
    """``CanFrame`` of a python-can message received at rig time ``rx_ns``; the data's hex without
    a copy when it fits (up to 64 bytes): the bridge makes one per frame read, ~1600 a second at
    400 Hz on classic CAN."""
    d = msg.data
    return CanFrame(
        seq=seq,
        stamp_ns=rx_ns,
        channel=channel,
        arbitration_id=msg.arbitration_id & 0x1FFFFFFF,
        is_extended_id=bool(msg.is_extended_id),
        is_fd=bool(msg.is_fd),
        bitrate_switch=bool(msg.bitrate_switch),
        is_error_frame=bool(msg.is_error_frame),
        data_hex=d.hex() if len(d) <= 64 else bytes(d[:64]).hex(),
    )


def imu_sample_msg(seq: int, rx_ns: int, dt_ns: int, s: Any) -> ImuSample:
    """``sensor/imu`` from a reassembled CAN sample (``hil.can.codec.DecodedSample``), stamped on arrival."""
    return ImuSample(
        seq=seq,
        stamp_ns=rx_ns,
        device_stamp_ns=s.device_stamp_ns,
        rx_stamp_ns=rx_ns,
        dt_ns=dt_ns,
        dtheta_b_rad=list(s.dtheta_b_rad),
        dvel_b_mps=list(s.dvel_b_mps),
        status=s.status,
    )
