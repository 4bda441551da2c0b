"""One receiver epoch the wire codec tests share (hil.wire.nmea, hil.wire.ubx)."""

from __future__ import annotations

from hil.wire.base import ReceiverEpoch
from hil.wire.gnss_time import utc_fields_to_gps_ns

T0 = utc_fields_to_gps_ns(2024, 5, 6, 12, 34, 56, 200_000_000)


def sample_epoch(gps_ns: int = T0, **kw: object) -> ReceiverEpoch:
    """A 3-D fix near Zurich moving at 2.3 m/s; ``kw`` overrides any field."""
    values: dict[str, object] = dict(
        gps_time_ns=gps_ns,
        lat_deg=47.28523316,
        lon_deg=8.56526500,
        alt_m=499.6,
        vel_ned_mps=(1.0, -2.0, 0.3),
        pos_sigma_ned_m=(0.46, 0.29, 0.64),
        vel_sigma_mps=(0.05, 0.05, 0.08),
        fix_type=3,
        num_sats=8,
        hdop=1.01,
        pdop=1.8,
        vdop=1.4,
    )
    values.update(kw)
    return ReceiverEpoch(**values)  # type: ignore[arg-type]
