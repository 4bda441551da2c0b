"""world: announces the run (time zero, scenario, speed) and publishes the truth trajectory.

Every emulator derives truth itself from the scenario in ``RunInfo``; world's ``truth`` topic is
the reference the recording and the live view compare estimates against. With ``wait_for`` it
holds time zero back until those services report ``waiting_run``, so nothing starts before the
recorder listens.

Restarted by ``hil up`` (option ``resume_run``: the RunInfo it had announced), world announces
the *same* run again -- same time zero, same scenario -- and resumes truth at the current rig
time with ``seq`` = truth sample index, so a restart never starts a second run nor re-sends the
past. ``imu_rate_hz`` overrides the scenario's IMU rate (the override travels in the scenario
text of RunInfo, so every service and a replay see the same rate).
"""

from __future__ import annotations

import argparse
import threading
import time
from typing import Any

import numpy as np

from hil.messages import RunInfo, ServiceStatus, Truth
from hil.runtime.builders import truth_msg
from hil.runtime.clock import RigClock, wall_ns
from hil.runtime.scenario_io import scenario_for_run, sha256_text
from hil.runtime.service import Service, run_service

TRUTH_BATCH = 10


class World(Service):
    name = "world"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        opts = ctx.options
        self.truth_rate_hz = float(opts.get("truth_rate_hz", 100.0))
        self.speed = float(opts.get("speed", 1.0))
        self.wait_for: set[str] = set(opts.get("wait_for", []))
        self.wait_timeout_s = float(opts.get("wait_timeout_s", 60.0))
        self.lead_s = float(opts.get("lead_s", 1.0))
        self._ready: set[str] = set()
        self._ready_event = threading.Event()

    def needs_run(self) -> bool:
        return False

    def setup(self) -> None:
        import hil.nav.trajectory  # noqa: F401 - before time zero
        from hil.nav.scenario import load_scenario, scenario_overrides

        name = self.ctx.options.get("scenario") or "straight_level"
        self.scenario = load_scenario(name)
        if self.ctx.options.get("imu_rate_hz"):
            self.scenario = scenario_overrides(
                self.scenario, imu_rate_hz=int(self.ctx.options["imu_rate_hz"])
            )
        if self.ctx.options.get("duration_s") is not None:
            self.duration_s = float(self.ctx.options["duration_s"])
        else:
            self.duration_s = float(self.scenario.duration_s)
        self.run_pub = self.publisher(self.keys.run(), RunInfo)
        self.truth_pub = self.publisher(self.keys.truth(), Truth)
        if self.wait_for:
            self.subscribe(self.keys.status("*"), ServiceStatus, self._on_status)

    def _on_status(self, st: ServiceStatus, _key: str) -> None:
        if st.service in self.wait_for and st.state in ("waiting_run", "running"):
            self._ready.add(st.service)
            if self._ready >= self.wait_for:
                self._ready_event.set()

    def run_loop(self, _run: Any, _clock: Any) -> None:
        resume = self.ctx.options.get("resume_run")
        if resume:
            # the announcements' seq continues in this process's restart generation (service.py)
            self._run_truth(RunInfo(**resume))
            return
        deadline = time.monotonic() + self.wait_timeout_s
        while self.wait_for and not self._ready_event.wait(0.1):
            if self.ctx.stop.is_set():
                return
            if time.monotonic() > deadline:
                missing = sorted(self.wait_for - self._ready)
                self.stats.error(
                    "errors.wait_for", f"started without {missing}: no status in {self.wait_timeout_s} s"
                )
                break
        if self.ctx.stop.is_set():
            return
        s = self.scenario
        start = wall_ns() + int(self.lead_s * 1e9)
        run = RunInfo(
            seq=0,
            stamp_ns=0,
            rig=self.keys.rig,
            start_epoch_ns=start,
            speed=self.speed,
            scenario=s.name,
            scenario_sha256=sha256_text(s.source_text),
            seed=s.seed,
            duration_s=self.duration_s,
            origin_lat_deg=s.origin_lat_deg,
            origin_lon_deg=s.origin_lon_deg,
            origin_alt_m=s.origin_alt_m,
            scenario_toml=s.source_text,
        )
        self._run_truth(run)

    def _run_truth(self, run: RunInfo) -> None:
        """Announce ``run`` at 1 Hz and publish truth from the current rig time to the end."""
        self.run_info = run
        self.clock = clock = RigClock(run.start_epoch_ns, run.speed)
        self.state = "running"
        from hil.nav.trajectory import TruthGenerator

        truth = TruthGenerator(scenario_for_run(run))
        threading.Thread(target=self._announce_loop, args=(run, clock), name="announce", daemon=True).start()
        dt_ns = round(1e9 / self.truth_rate_hz)
        n_total = int(run.duration_s * 1e9) // dt_ns + 1
        k = max(0, clock.now_ns() // dt_ns) if self.ctx.options.get("resume_run") else 0
        if k:
            self.emit_event("resumed", f"world restarted: same run, truth resumes at sample {k}")
        while k < n_total and not self.ctx.stop.is_set():
            n = min(TRUTH_BATCH, n_total - k)
            t_last = (k + n - 1) * dt_ns
            clock.sleep_until(t_last, self.ctx.stop)
            if self.ctx.stop.is_set():
                break
            t = np.arange(k, k + n, dtype=np.int64) * dt_ns
            b = truth.sample(t)
            for i in range(n):
                self.truth_pub.put(truth_msg(k + i, int(t[i]), b, i))  # seq = sample index: restart-safe
            k += n
        self.ctx.stop.wait()

    def _announce_loop(self, run: RunInfo, clock: RigClock) -> None:
        """RunInfo at 1 Hz (wall clock), so late joiners -- a restarted service -- learn time zero."""
        while True:
            self.run_pub.put(
                RunInfo(
                    **{**_fields(run), "seq": self.run_pub.next_seq(), "stamp_ns": max(clock.now_ns(), 0)}
                )
            )
            if self.ctx.stop.wait(1.0):
                return


def _fields(run: RunInfo) -> dict[str, Any]:
    return {f: getattr(run, f) for f in run.__struct_fields__}


SERVICE = World


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hil service world")
    ap.add_argument("--rig", default="default")
    ap.add_argument("--scenario", default="straight_level")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--wait-for", default="", help="comma-separated services to wait for before time zero")
    a = ap.parse_args(argv)
    opts = {
        "scenario": a.scenario,
        "duration_s": a.duration,
        "speed": a.speed,
        "wait_for": [s for s in a.wait_for.split(",") if s],
    }
    return run_service(World, a.rig, opts)
