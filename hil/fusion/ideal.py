"""The rig's emulator cores as the fusion core takes them, with ideal timing.

The IMU samples and GNSS fixes a scenario's emulators make, stamped at their time of validity
(device = receive = validity: no clock, no bus, no latency) and in the fusion's total order. What
the unit tests and the offline benches feed ``FusionCore.push`` when the question is the
estimators, not the transport; ``hil sim`` is the same emulators through the whole rig.
"""

from __future__ import annotations

from hil.messages import GnssFix, ImuSample
from hil.nav.scenario import Scenario
from hil.nav.trajectory import TruthGenerator, truth_for
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import ImuEmulatorCore, sensor_rng


def ideal_streams(s: Scenario, truth: TruthGenerator | None = None) -> tuple[list[ImuSample], list[GnssFix]]:
    """The scenario's IMU samples and GNSS fixes over its whole duration, each stream in order."""
    truth = truth or truth_for(s)
    imu = ImuEmulatorCore(s, truth, sensor_rng(s.seed, "imu")).next_batch(int(s.duration_s * s.imu.rate_hz))
    gnss = GnssEmulatorCore(s, truth, sensor_rng(s.seed, "gnss")).next_batch(int(s.duration_s * 1e9))
    dt_ns = round(1e9 / s.imu.rate_hz)
    imus = [
        ImuSample(
            seq=k,
            stamp_ns=int(t),
            device_stamp_ns=int(t),
            rx_stamp_ns=int(t),
            dt_ns=dt_ns,
            dtheta_b_rad=imu.dtheta_b_rad[k].tolist(),
            dvel_b_mps=imu.dvel_b_mps[k].tolist(),
        )
        for k, t in enumerate(imu.t_ns)
    ]
    fixes = [
        GnssFix(
            seq=i,
            stamp_ns=int(t),
            device_stamp_ns=int(t),
            rx_stamp_ns=int(t),
            lat_deg=float(gnss.lat_deg[i]),
            lon_deg=float(gnss.lon_deg[i]),
            alt_m=float(gnss.alt_m[i]),
            pos_ned_m=gnss.pos_ned_m[i].tolist(),
            vel_ned_mps=gnss.vel_ned_mps[i].tolist(),
            pos_sigma_m=gnss.pos_sigma_m[i].tolist(),
            vel_sigma_mps=gnss.vel_sigma_mps[i].tolist(),
            fix_type=int(gnss.fix_type[i]),
            num_sats=int(gnss.num_sats[i]),
            hdop=float(gnss.hdop[i]),
        )
        for i, t in enumerate(gnss.t_valid_ns)
    ]
    return imus, fixes


def ideal_inputs(s: Scenario, truth: TruthGenerator | None = None) -> list[ImuSample | GnssFix]:
    """Both streams merged in the fusion's total order (stamp, IMU before GNSS, seq)."""
    imus, fixes = ideal_streams(s, truth)
    out: list[ImuSample | GnssFix] = [*imus, *fixes]
    out.sort(key=lambda m: (m.stamp_ns, 0 if m.sensor == "imu" else 1, m.seq))
    return out
