"""``hil bench physics``: truth + IMU generation and strapdown throughput, 1 h at 400 Hz.

Also states the ideal-sensor free-INS error on the default and a turning scenario, since the
same run produces it.
"""

from __future__ import annotations

import time

import numpy as np

from hil.bench import write_section
from hil.nav.earth import lla_to_ned
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nav.strapdown import strapdown_from_initial, strapdown_run
from hil.nav.trajectory import TruthGenerator
from hil.runtime.argtypes import OneLineParser, duration_s
from hil.sensors.imu import ImuEmulatorCore, sensor_rng


def _ideal_free_ins_error_m(name: str, duration_s: float, rate: int) -> float:
    s = scenario_overrides(load_scenario(name), duration_s=duration_s, imu_rate_hz=rate)
    tg = TruthGenerator(s)
    n = round(duration_s * rate)
    t = (np.arange(n + 1, dtype=np.int64) * 1_000_000_000) // rate
    dth, dv = tg.increments(t[:-1], t[1:])
    _, tr = strapdown_run(strapdown_from_initial(tg.initial_state()), dth, dv, 1 / rate, rate)
    truth = tg.sample(t[tr.step.astype(int)])
    pos = lla_to_ned(tr.lat_rad, tr.lon_rad, tr.alt_m, tg.origin_lat_rad, tg.origin_lon_rad, tg.origin_alt_m)
    return float(np.linalg.norm(pos - truth.pos_ned_m, axis=1).max())


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench physics")
    ap.add_argument("--duration-s", type=duration_s, default=3600.0)
    ap.add_argument("--rate-hz", type=int, default=400)
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    dur, rate = args.duration_s, args.rate_hz
    n = round(dur * rate)

    s = scenario_overrides(load_scenario("straight_level"), duration_s=dur, imu_rate_hz=rate)
    t0 = time.perf_counter()
    tg = TruthGenerator(s)
    imu = ImuEmulatorCore(s, tg, sensor_rng(s.seed, "imu"))
    batches = [imu.next_batch(min(4000, n - k)) for k in range(0, n, 4000)]
    gen_s = time.perf_counter() - t0
    dth = np.concatenate([b.dtheta_b_rad for b in batches])
    dv = np.concatenate([b.dvel_b_mps for b in batches])

    t0 = time.perf_counter()
    strapdown_run(strapdown_from_initial(tg.initial_state()), dth, dv, 1 / rate, rate)
    sd_s = time.perf_counter() - t0

    # the live path: small batches
    small = {}
    for bs in (1, 10, 40):
        core = ImuEmulatorCore(s, tg, sensor_rng(s.seed, "imu"))
        m = 2000 // bs
        t0 = time.perf_counter()
        for _ in range(m):
            core.next_batch(bs)
        small[bs] = (time.perf_counter() - t0) / m

    err_sl = _ideal_free_ins_error_m("straight_level", dur, rate)
    uav = load_scenario("uav_survey").duration_s
    err_uav = _ideal_free_ins_error_m("uav_survey", uav, rate)
    err_uav_1h = _ideal_free_ins_error_m("uav_survey", dur, rate)

    rows = [
        (
            f"truth + IMU generation (tactical, straight_level), {dur:.0f} s at {rate} Hz, batches of 4000",
            f"{gen_s:.1f} s ({dur / gen_s:.0f}× real time)",
        ),
        (
            f"strapdown, {n} steps at {rate} Hz",
            f"{sd_s:.1f} s ({dur / sd_s:.0f}× real time, {sd_s / n * 1e6:.1f} µs/step)",
        ),
        (
            "`ImuEmulatorCore.next_batch` per call, batch 1 / 10 / 40",
            " / ".join(f"{small[b] * 1e3:.2f}" for b in (1, 10, 40)) + " ms",
        ),
        (f"ideal-IMU free INS, straight_level {dur:.0f} s, max position error", f"{err_sl:.2e} m"),
        (
            f"ideal-IMU free INS, uav_survey ({uav:.0f} s, 7 × 180° coordinated turns), max error",
            f"{err_uav:.3f} m",
        ),
        (f"same, uav_survey padded to {dur:.0f} s (straight after the turns)", f"{err_uav_1h:.3f} m"),
    ]
    md = "| measurement | value |\n| --- | --- |\n" + "\n".join(f"| {a} | {b} |" for a, b in rows)
    print(md.strip())
    if not args.no_write:
        write_section("physics", md, " ".join(["hil", "bench", "physics", *argv]))
    return 0
