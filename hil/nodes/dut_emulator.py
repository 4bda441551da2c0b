"""A stand-in navigation box on the CAN bus, for showing device-under-test scoring.

It sends truth plus a slowly wandering position error (first-order Gauss-Markov, seeded from
the scenario seed and ``"dut"``) as the unit's own DBC frames at its output rate; the CAN bridge
decodes them with the same mapping into ``nav/<name>``, scored against truth like the rig's
estimators (``hil up --dut MAPPING --dut-emulator``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil.can.dut_emulator import DutNavEncoder, load_dut
from hil.nav.scenario import scenario_for_run
from hil.nav.trajectory import truth_for
from hil.nodes.base import CAN_TX, CanBurst, CanWriterOptions, Node, OptionsError, Out
from hil.sensors.imu import sensor_rng


class DutEmulatorOptions(CanWriterOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    dut_mapping: str | None = None  # the unit's mapping TOML (required)
    rate_hz: float = 10.0  # solutions per second
    sigma_h_m: float = 1.5  # horizontal error, 1 sigma (vertical: twice that)
    tau_s: float = 60.0  # correlation time of the error


class DutEmulatorNode(Node):
    name = "dut_emulator"
    Options = DutEmulatorOptions
    writes_can = True

    def __init__(self, run: Any, options: DutEmulatorOptions | None = None) -> None:
        super().__init__(run, options)
        o: DutEmulatorOptions = self.options  # type: ignore[assignment]
        if not o.dut_mapping:
            raise OptionsError("dut_emulator: option dut_mapping is required (a DUT mapping TOML)")
        try:
            db, m = load_dut(o.dut_mapping)
        except ValueError as err:  # a bad mapping or DBC: one line (OptionsError), no traceback
            raise OptionsError(f"dut_emulator: option dut_mapping: {err}") from None
        self.encoder = DutNavEncoder(db, m)
        s = scenario_for_run(run)
        self.truth = truth_for(s)
        self.rng = sensor_rng(s.seed, "dut")
        self.dt_ns = round(1e9 / o.rate_hz)
        self.n_total = int(run.duration_s * o.rate_hz)
        self.phi = math.exp(-1.0 / (o.rate_hz * o.tau_s))
        self.sigma = np.array([o.sigma_h_m, o.sigma_h_m, 2 * o.sigma_h_m])
        self.err = self.rng.standard_normal(3) * self.sigma
        self.k = 1

    def next_tick_ns(self) -> int | None:
        return self.k * self.dt_ns if self.k <= self.n_total else None

    def tick(self, now_ns: int) -> list[Out]:
        outs: list[Out] = []
        while self.k <= self.n_total and self.k * self.dt_ns <= now_ns:
            outs.append(self._solution(self.k))
            self.k += 1
        return outs

    def _solution(self, k: int) -> Out:
        tb = self.truth.sample(np.array([k * self.dt_ns], dtype=np.int64))
        # x_k = phi x_{k-1} + sqrt(1 - phi^2) sigma w_k  (stationary Gauss-Markov)
        self.err = self.phi * self.err + math.sqrt(1 - self.phi**2) * self.rng.standard_normal(3) * self.sigma
        o: DutEmulatorOptions = self.options  # type: ignore[assignment]
        values = DutNavEncoder.values_from_truth(
            math.degrees(tb.lat_rad[0]),
            math.degrees(tb.lon_rad[0]),
            float(tb.alt_m[0]),
            tb.vel_ned_mps[0],
            tb.q_nb[0],
            self.err,
            o.sigma_h_m,
            2 * o.sigma_h_m,
        )
        self.inc("solutions")
        return CAN_TX, CanBurst(self.encoder.encode(values), k * self.dt_ns, k)
