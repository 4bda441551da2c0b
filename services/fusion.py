"""fusion: every estimator on the same synchronised inputs, each on ``nav/<estimator>``.

Zenoh callbacks only enqueue; one worker thread feeds the pure ``FusionCore`` so its decisions do
not depend on thread scheduling beyond arrival order, and journals every input it dropped as
late on ``fusion/journal`` -- with the recorded inputs, that is all ``hil rerun`` needs.

A fusion restarted mid-run (option ``resume`` from ``hil up --restart``) re-aligns: it waits for
its first IMU input and builds every estimator from the run's truth at that input's stamp (an
in-flight re-alignment; the rig knows truth, a real unit would use its last good solution), then
numbers its outputs after ``imu_seq // output_every + 1`` so no seq repeats one from before the
death. It says so in a ``realigned`` event. ``hil rerun --verify`` reproduces runs without a
fusion restart; after one, the outputs of the second process are not those of an uninterrupted
run by design, and rerun reports the first difference.
"""

from __future__ import annotations

import argparse
import queue
import time
from typing import Any

from hil.fusion.core import FREE_INS, FusionConfig, FusionCore
from hil.messages import FusionJournal, GnssFix, ImuSample, NavSolution, RunInfo
from hil.record.lockstep import ack_key, encode_ack
from hil.runtime.clock import RigClock
from hil.runtime.scenario_io import scenario_for_run
from hil.runtime.service import Service, run_service

JOURNAL_PERIOD_S = 0.5
STOP_DRAIN_S = 5.0  # at most this long consuming the backlog after SIGTERM


def default_estimators() -> tuple[str, ...]:
    try:
        from hil.estimators.registry import DEFAULT_ESTIMATORS

        return tuple(DEFAULT_ESTIMATORS)
    except ImportError:
        return ()


class Fusion(Service):
    name = "fusion"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.inbox: queue.SimpleQueue[ImuSample | GnssFix | None] = queue.SimpleQueue()
        self.core: FusionCore | None = None

    def setup(self) -> None:
        import hil.estimators.registry
        import hil.nav.trajectory  # noqa: F401

        self.subscribe(self.keys.synced("imu"), ImuSample, lambda m, _k: self.inbox.put(m))
        self.subscribe(self.keys.synced("gnss"), GnssFix, lambda m, _k: self.inbox.put(m))

    def extra_status(self) -> dict[str, int]:
        core = self.core
        out = {"inbox": self.inbox.qsize()}
        if core is not None:
            out.update(core.health())
        return out

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:

        opts = self.ctx.options
        names = tuple(opts.get("estimators") or default_estimators())
        cfg = FusionConfig(
            estimators=names,
            lag_ns=int(float(opts.get("lag_s", 0.2)) * 1e9),
            output_every=int(opts.get("output_every", 8)),
        )
        scenario = scenario_for_run(run)
        first: ImuSample | GnssFix | None = None
        held: list[ImuSample | GnssFix] = []
        if opts.get("resume"):
            while first is None and not self.ctx.stop.is_set():
                try:
                    m = self.inbox.get(timeout=0.1)
                except queue.Empty:
                    continue
                if m is not None:
                    held.append(m)
                    if m.sensor == "imu":
                        first = m
            if first is None:
                return
        align_ns = first.stamp_ns if first is not None else 0
        self.core = core = FusionCore.for_scenario(scenario, cfg, align_ns=align_ns)
        if first is not None:
            core.start_output_seq(first.seq // cfg.output_every + 1)
            held = [m for m in held if m.stamp_ns >= align_ns]  # nothing from before the alignment
            self.emit_event(
                "realigned",
                f"fusion restarted: estimators re-aligned from truth at t={align_ns / 1e9:.3f} s "
                f"(imu seq {first.seq}); outputs numbered from {first.seq // cfg.output_every + 1}",
            )
        from hil.record.rerun import FUSION_CONFIG_EVENT, fusion_config_detail

        self.emit_event(FUSION_CONFIG_EVENT, fusion_config_detail(cfg))
        pubs = {n: self.publisher(self.keys.nav(n), NavSolution) for n in (FREE_INS, *names)}
        journal = self.publisher(self.keys.journal(), FusionJournal)
        # lockstep replay: say how many inputs were pushed (hil/record/lockstep.py)
        ack = self.ctx.session.declare_publisher(ack_key(self.ctx.rig))
        pushed = 0
        last_journal = time.monotonic()
        consumed_at_journal = 0

        def emit(sols: list[NavSolution]) -> None:
            for sol in sols:
                pubs[sol.estimator].put(sol)

        def write_journal() -> None:
            nonlocal consumed_at_journal
            journal.put(core.journal(journal.next_seq(), clock.now_ns()))
            consumed_at_journal = core.consumed

        while not self.ctx.stop.is_set():
            try:
                msg = held.pop(0) if held else self.inbox.get(timeout=0.1)
            except queue.Empty:
                msg = None
            if msg is not None:
                emit(core.push(msg))
                pushed += 1
                ack.put(encode_ack(pushed))
            if time.monotonic() - last_journal >= JOURNAL_PERIOD_S:
                last_journal = time.monotonic()
                write_journal()
                ack.put(encode_ack(pushed))
            if getattr(core, "last_error", ""):
                self.stats.error("errors.estimator", core.last_error)
                core.last_error = ""
        # stop: drain what had arrived (bounded: a fusion behind a backlog must still stop on
        # time), release the buffered tail, journal it. Inputs left unconsumed are not journaled
        # as dropped: rerun simply computes a few outputs more than were published.
        drain_until = time.monotonic() + STOP_DRAIN_S
        while time.monotonic() < drain_until:
            try:
                msg = held.pop(0) if held else self.inbox.get_nowait()
            except queue.Empty:
                break
            if msg is not None:
                emit(core.push(msg))
        emit(core.flush())
        write_journal()
        _ = consumed_at_journal


SERVICE = Fusion


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hil service fusion")
    ap.add_argument("--rig", default="default")
    ap.add_argument("--estimators", default="", help="comma-separated (default: the registry's defaults)")
    ap.add_argument("--lag", type=float, default=0.2, help="watermark lag in seconds")
    a = ap.parse_args(argv)
    opts: dict[str, Any] = {"lag_s": a.lag}
    if a.estimators:
        opts["estimators"] = [e for e in a.estimators.split(",") if e]
    return run_service(Fusion, a.rig, opts)
