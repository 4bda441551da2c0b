"""The world: announces the run and publishes the truth trajectory.

Every emulator derives truth itself from the scenario in ``RunInfo``; the ``truth`` topic is the
reference the recording and the live view compare estimates against (100 Hz, computed in blocks
of 0.1 s of rig time; the trajectory does not depend on the block). ``RunInfo`` goes out at start
and, with ``announce_every_s``, again periodically so late joiners -- a restarted service, a
monitor -- learn time zero. Deciding the run (time zero, scenario, speed) is the runner's: live,
``world``'s service waits for the other services and picks a wall-clock instant; ``hil sim``
starts at zero.

Restarted (option ``resume``), world announces the same run again and resumes truth at the
current rig time with ``seq`` = truth sample index, so a restart never starts a second run nor
re-sends the past.
"""

from __future__ import annotations

import hashlib
from typing import Any

import msgspec
import numpy as np

from hil.messages import RunInfo
from hil.nav.limits import MAX_DURATION_S, MAX_SPEED, MIN_SPEED
from hil.nav.scenario import scenario_for_run
from hil.nav.trajectory import truth_for
from hil.nodes.base import Node, NodeOptions, Out
from hil.nodes.builders import truth_msg

BLOCK_NS = 1_000_000_000  # truth computed per second of rig time (its bits do not depend on the block)


class WorldOptions(NodeOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    scenario: str = "straight_level"  # built-in name or TOML path
    duration_s: float | None = None  # None: the scenario's
    speed: float = 1.0  # rig seconds per wall second
    imu_rate_hz: int | None = None  # override the scenario's IMU rate (travels in RunInfo's text)
    fd: bool = False  # the IMU on CAN FD (hil up --fd): said in RunInfo (``imu_can_fd``)
    truth_rate_hz: float = 100.0
    announce_every_s: float = 1.0  # RunInfo again this often (0: once)
    truth_batch: int = 10  # publish truth this many samples at a time (hil sim: 1, each at its time)
    # services whose status must say ready before time zero
    wait_for: list[str] = msgspec.field(default_factory=list)
    wait_timeout_s: float = 60.0
    lead_s: float = 1.0  # time zero this long after the run is decided
    resume_run: dict[str, Any] | None = None  # a restarted world: the run it had announced

    def __post_init__(self) -> None:
        # compose hands HIL_DURATION_S/HIL_SPEED straight through: the same limits as hil up's flags
        if self.duration_s is not None and not 0 < self.duration_s <= MAX_DURATION_S:
            raise ValueError(f"duration_s must be in (0, {MAX_DURATION_S:g}] s, got {self.duration_s!r}")
        if not MIN_SPEED <= self.speed <= MAX_SPEED:
            raise ValueError(f"speed must be in [{MIN_SPEED:g}, {MAX_SPEED:g}], got {self.speed!r}")


def run_info(
    scenario: Any,
    *,
    rig: str,
    start_epoch_ns: int,
    speed: float,
    duration_s: float | None,
    imu_can_fd: bool = False,
) -> RunInfo:
    """The run of ``scenario`` (a ``hil.nav.scenario.Scenario``): what every runner announces --
    ``hil up`` with time zero on the wall clock, ``hil sim`` with epoch 0."""
    return RunInfo(
        seq=0,
        stamp_ns=0,
        rig=rig,
        start_epoch_ns=start_epoch_ns,
        speed=speed,
        scenario=scenario.name,
        scenario_sha256=hashlib.sha256(scenario.source_text.encode()).hexdigest(),
        seed=scenario.seed,
        duration_s=float(duration_s if duration_s is not None else scenario.duration_s),
        origin_lat_deg=scenario.origin_lat_deg,
        origin_lon_deg=scenario.origin_lon_deg,
        origin_alt_m=scenario.origin_alt_m,
        scenario_toml=scenario.source_text,
        imu_can_fd=imu_can_fd,
    )


class WorldNode(Node):
    name = "world"
    Options = WorldOptions
    outputs = ("run", "truth")

    def __init__(self, run: RunInfo, options: WorldOptions | None = None) -> None:
        super().__init__(run, options)
        opts: WorldOptions = self.options  # type: ignore[assignment]
        self.truth = truth_for(scenario_for_run(run))
        self.dt_ns = round(1e9 / opts.truth_rate_hz)
        self.n_total = int(run.duration_s * 1e9) // self.dt_ns + 1
        self.k = 0
        self.announce_ns = round(opts.announce_every_s * 1e9)
        self._next_announce: int | None = None
        self._block: Any = None
        self._block_k0 = 0

    def start(self, now_ns: int) -> list[Out]:
        outs = [self._announce(now_ns)]
        if self.options.resume:
            self.k = min(max(0, now_ns // self.dt_ns), self.n_total)
            detail = f"world restarted: same run, truth resumes at sample {self.k}"
            outs.append(self.event("resumed", detail, now_ns))
        return outs

    def _announce(self, now_ns: int) -> Out:
        fields = {f: getattr(self.run, f) for f in self.run.__struct_fields__}
        fields.update(seq=self.next_seq("run"), stamp_ns=max(now_ns, 0))
        if self.announce_ns > 0:
            self._next_announce = now_ns + self.announce_ns
        return "run", RunInfo(**fields)

    def next_tick_ns(self) -> int | None:
        """The next batch of truth (at its last sample's time); an announcement before it;
        nothing after the run's last sample."""
        if self.k >= self.n_total:
            return None
        batch = max(1, self.options.truth_batch)  # type: ignore[attr-defined]
        t = (min(self.k + batch, self.n_total) - 1) * self.dt_ns
        return t if self._next_announce is None else min(t, self._next_announce)

    def tick(self, now_ns: int) -> list[Out]:
        outs: list[Out] = []
        if self._next_announce is not None and now_ns >= self._next_announce:
            outs.append(self._announce(now_ns))
        while self.k < self.n_total and self.k * self.dt_ns <= now_ns:
            b, i = self._row(self.k)
            outs.append(("truth", truth_msg(self.k, self.k * self.dt_ns, b, i)))  # seq = sample index
            self.k += 1
        return outs

    def _row(self, k: int) -> tuple[Any, int]:
        b = self._block
        if b is None or not self._block_k0 <= k < self._block_k0 + len(b.alt_m):
            t0 = k * self.dt_ns
            t_end = (t0 // BLOCK_NS + 1) * BLOCK_NS
            n = min(self.n_total, (t_end - 1) // self.dt_ns + 1) - k
            self._block = b = self.truth.sample(np.arange(k, k + max(1, n), dtype=np.int64) * self.dt_ns)
            self._block_k0 = k
        return b, k - self._block_k0
