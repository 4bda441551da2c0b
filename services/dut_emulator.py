"""dut_emulator: a stand-in navigation box on the CAN bus, for showing device-under-test scoring.

It sends truth plus a slowly wandering position error (first-order Gauss-Markov, seeded from the
scenario seed and "dut") as the unit's own DBC frames at its output rate; ``can_bridge`` decodes
them with the same mapping into ``nav/<name>``, scored against truth like the rig's estimators.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np

from hil.messages import RunInfo
from hil.runtime.clock import RigClock
from hil.runtime.scenario_io import scenario_for_run
from hil.runtime.service import Service, run_service


class DutEmulator(Service):
    name = "dut_emulator"

    def setup(self) -> None:
        # every import before time zero, not after (hil.sensors.imu pulls scipy: ~3 s)
        import hil.can.bus
        import hil.nav.trajectory
        import hil.sensors.imu  # noqa: F401
        from hil.can.dut_emulator import DutNavEncoder, load_dut

        mapping = self.ctx.options.get("dut_mapping")
        if not mapping:
            raise ValueError("dut_emulator needs the option dut_mapping (a DUT mapping TOML)")
        db, m = load_dut(mapping)
        self.encoder = DutNavEncoder(db, m)

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        from hil.can.bus import open_can_bus
        from hil.can.dut_emulator import DutNavEncoder
        from hil.nav.trajectory import TruthGenerator
        from hil.sensors.imu import sensor_rng

        opts = self.ctx.options
        s = scenario_for_run(run)
        truth = TruthGenerator(s)
        rng = sensor_rng(s.seed, "dut")
        rate_hz = float(opts.get("rate_hz", 10.0))
        sigma_h = float(opts.get("sigma_h_m", 1.5))
        tau_s = float(opts.get("tau_s", 60.0))
        dt_ns = round(1e9 / rate_hz)
        phi = math.exp(-1.0 / (rate_hz * tau_s))
        err = rng.standard_normal(3) * np.array([sigma_h, sigma_h, 2 * sigma_h])
        bus, _desc = open_can_bus(
            opts.get("channel", "vcan0"), opts.get("interface"), rig=self.keys.rig, session=self.ctx.session
        )
        n_total = int(run.duration_s * rate_hz)
        try:
            for k in range(1, n_total + 1):
                clock.sleep_until(k * dt_ns, self.ctx.stop)
                if self.ctx.stop.is_set():
                    break
                tb = truth.sample(np.array([k * dt_ns], dtype=np.int64))
                # x_k = phi x_{k-1} + sqrt(1 - phi^2) sigma w_k  (stationary Gauss-Markov)
                err = phi * err + math.sqrt(1 - phi * phi) * rng.standard_normal(3) * np.array(
                    [sigma_h, sigma_h, 2 * sigma_h]
                )
                values = DutNavEncoder.values_from_truth(
                    math.degrees(tb.lat_rad[0]),
                    math.degrees(tb.lon_rad[0]),
                    float(tb.alt_m[0]),
                    tb.vel_ned_mps[0],
                    tb.q_nb[0],
                    err,
                    sigma_h,
                    2 * sigma_h,
                )
                for frame in self.encoder.encode(values):
                    try:
                        bus.send(frame, timeout=0.05)
                    except Exception as e:  # a full queue or a bus error: count, go on
                        self.stats.error("errors.can.send", f"{type(e).__name__}: {e}")
                self.stats.count_rate("out.dut.solutions")
            self.ctx.stop.wait()
        finally:
            bus.shutdown()


SERVICE = DutEmulator


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hil service dut_emulator")
    ap.add_argument("--rig", default="default")
    ap.add_argument("--dut-mapping", required=True)
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument("--interface", default=None)
    a = ap.parse_args(argv)
    opts: dict[str, Any] = {"dut_mapping": a.dut_mapping, "channel": a.channel, "interface": a.interface}
    return run_service(DutEmulator, a.rig, opts)
