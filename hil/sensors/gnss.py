"""GNSS receiver emulator core: truth at the time of validity plus the seed paper's error model.

Position error per NED axis at epoch time t (validity):

    e(t) = σ w(t)                                   white, independent per epoch
         + A_slow sin(2π t / P_slow + φ)             slow geometry/DOP component, P ≈ 2–3 Schuler
         + Σ active jumps/pulses/spoofs (offset_ned_m)  scenario events
    velocity: σ_v w_v(t) + A_slow (2π/P) cos(…) + active velocity glitches

Outages (``gnss_outage`` events) omit the epochs entirely: the receiver sends nothing, so the
consumer sees a gap (not a fix_type 0 message). The output time is validity + latency + jitter,
jitter uniform in [0, jitter_s), latency changed by ``gnss_latency`` events. An optional lever
arm puts the antenna at ``lever_arm_b_m`` in body axes. Noise for every epoch — including the
omitted ones — comes from dedicated child generators in epoch order, so the stream is the same
however the caller slices it and whatever the outages.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.nav.attitude import quat_to_dcm
from hil.nav.earth import cross, earth_rate_ned, mat_vec, ned_to_lla, transport_rate_ned
from hil.nav.scenario import Scenario
from hil.nav.trajectory import TruthGenerator
from hil.nav.types import F64, I64

_NS = 1_000_000_000
FIX_NONE = 0
FIX_3D = 3


@dataclass(frozen=True)
class GnssBatch:
    """Receiver epochs in validity order; times are true times (ns since run start)."""

    t_valid_ns: I64  # (n,) time of validity
    t_output_ns: I64  # (n,) when the receiver outputs it (= validity + latency + jitter)
    pos_ned_m: F64  # (n, 3) antenna position relative to the scenario origin
    vel_ned_mps: F64  # (n, 3)
    lat_deg: F64  # (n,)
    lon_deg: F64  # (n,)
    alt_m: F64  # (n,)
    pos_sigma_m: F64  # (n, 3) reported 1σ (the configured white σ)
    vel_sigma_mps: F64  # (n, 3)
    fix_type: I64  # (n,) 0 none, 3 = 3D fix (outage epochs are omitted, so always 3 here)
    num_sats: I64  # (n,)
    hdop: F64  # (n,)


class GnssEmulatorCore:
    """Streams GNSS epochs for a scenario up to a requested time of validity."""

    def __init__(self, scenario: Scenario, truth: TruthGenerator, rng: np.random.Generator) -> None:
        self.scenario = scenario
        self.truth = truth
        cfg = scenario.gnss
        self.cfg = cfg
        self.period_ns = round(_NS / cfg.rate_hz)
        self.next_epoch = 0
        g_phase, self._g_pos, self._g_vel, self._g_jit = rng.spawn(4)
        self.slow_phase_rad = g_phase.uniform(0.0, 2.0 * math.pi, 3)
        self._events = scenario.events

    def _event_offsets(self, t_s: F64) -> tuple[F64, F64, np.ndarray, F64, F64, F64]:
        """Position and velocity offsets, outage mask, latency, jitter and the position σ a
        spoofer claims (NaN: the receiver's own) at each epoch time."""
        n = t_s.shape[0]
        dpos = np.zeros((n, 3))
        dvel = np.zeros((n, 3))
        out = np.zeros(n, dtype=bool)
        lat = np.full(n, self.cfg.latency_s)
        jit = np.full(n, self.cfg.jitter_s)
        claim = np.full(n, np.nan)
        for ev in self._events:
            on = (t_s >= ev.t_start_s) & (t_s < (np.inf if ev.t_end_s is None else ev.t_end_s))
            if ev.kind == "gnss_outage":
                out |= on
            elif ev.kind in ("gnss_jump", "gnss_pulse", "gnss_spoof"):
                dpos[on] += np.asarray(ev.params["offset_ned_m"])
                if ev.kind == "gnss_spoof":
                    claim[on] = ev.params["sigma_m"]
            elif ev.kind == "gnss_velocity_glitch":
                dvel[on] += np.asarray(ev.params["offset_ned_mps"])
            elif ev.kind == "gnss_latency":  # events in file order: a later one overrides
                lat[on] = ev.params["latency_s"]
                if "jitter_s" in ev.params:
                    jit[on] = ev.params["jitter_s"]
        return dpos, dvel, out, lat, jit, claim

    def add_event(self, event: Any) -> None:
        """A fault from now on (a run-time command, as a ``ScenarioEvent``): epochs not yet
        returned see it."""
        self._events = (*self._events, event)

    def next_epoch_ns(self) -> int | None:
        """Time of validity of the next epoch not yet returned (None past the run's end)."""
        t = self.next_epoch * self.period_ns
        return t if t <= self.truth.duration_ns else None

    def has_due(self, until_t_valid_ns: int) -> bool:
        """Whether :meth:`next_batch` would return an epoch: lets a polling caller skip empty work."""
        return min(int(until_t_valid_ns), self.truth.duration_ns) // self.period_ns >= self.next_epoch

    def next_batch(self, until_t_valid_ns: int) -> GnssBatch:
        """All epochs not yet returned with validity ≤ ``until_t_valid_ns`` (and ≤ duration)."""
        last = min(int(until_t_valid_ns), self.truth.duration_ns) // self.period_ns
        k = np.arange(self.next_epoch, max(self.next_epoch, last + 1), dtype=np.int64)
        self.next_epoch += len(k)
        n = len(k)
        cfg = self.cfg
        w_pos = self._g_pos.standard_normal((n, 3))
        w_vel = self._g_vel.standard_normal((n, 3))
        u_jit = self._g_jit.random(n)
        t_ns = k * self.period_ns
        t_s = t_ns.astype(np.float64) * 1e-9
        tb = self.truth.sample(t_ns)
        pos = tb.pos_ned_m.copy()
        vel = tb.vel_ned_mps.copy()
        if any(cfg.lever_arm_b_m):
            # antenna = IMU + C_nb l;  v_ant = v + C_nb (ω_nb^b × l),  ω_nb^b = ω_ib^b − C_bn ω_in^n
            c_nb = quat_to_dcm(tb.q_nb)
            lever = np.broadcast_to(np.asarray(cfg.lever_arm_b_m), (n, 3))
            w_in = earth_rate_ned(tb.lat_rad) + transport_rate_ned(tb.lat_rad, tb.alt_m, vel)
            w_nb_b = tb.w_ib_b_radps - mat_vec(np.swapaxes(c_nb, -1, -2), w_in)
            pos += mat_vec(c_nb, lever)
            vel += mat_vec(c_nb, cross(w_nb_b, lever))
        amp = np.asarray(cfg.slow_amplitude_m)
        arg = 2.0 * np.pi * t_s[:, None] / cfg.slow_period_s + self.slow_phase_rad
        dpos, dvel, outage, latency, jitter, claim = self._event_offsets(t_s)
        pos += np.asarray(cfg.pos_sigma_m) * w_pos + amp * np.sin(arg) + dpos
        vel += (
            np.asarray(cfg.vel_sigma_mps) * w_vel
            + amp * (2.0 * np.pi / cfg.slow_period_s) * np.cos(arg)
            + dvel
        )
        t_out = t_ns + np.round((latency + jitter * u_jit) * 1e9).astype(np.int64)
        # satellites follow the slow geometry: ±2 around nominal, HDOP ∝ 1/√sats
        geom = np.sin(2.0 * np.pi * t_s / cfg.slow_period_s + self.slow_phase_rad[0])
        sats = np.maximum(4, cfg.num_sats + np.round(2.0 * geom)).astype(np.int64)
        hdop = cfg.hdop * np.sqrt(cfg.num_sats / sats)
        keep = ~outage
        lat_r, lon_r, alt = ned_to_lla(
            pos[keep], self.truth.origin_lat_rad, self.truth.origin_lon_rad, self.truth.origin_alt_m
        )
        m = int(keep.sum())
        pos_sigma = np.tile(np.asarray(cfg.pos_sigma_m), (m, 1))
        spoofed = ~np.isnan(claim[keep])
        pos_sigma[spoofed] = claim[keep][spoofed, None]  # a spoofer claims a precise fix
        return GnssBatch(
            t_valid_ns=t_ns[keep],
            t_output_ns=t_out[keep],
            pos_ned_m=pos[keep],
            vel_ned_mps=vel[keep],
            lat_deg=np.degrees(lat_r),
            lon_deg=np.degrees(lon_r),
            alt_m=alt,
            pos_sigma_m=pos_sigma,
            vel_sigma_mps=np.tile(np.asarray(cfg.vel_sigma_mps), (m, 1)),
            fix_type=np.full(m, FIX_3D, dtype=np.int64),
            num_sats=sats[keep],
            hdop=hdop[keep],
        )
