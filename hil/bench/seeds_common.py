"""What ``hil bench seeds`` and its UAV comparison share: the seed-000 GNSS model and the report.

Kept apart from both so that :mod:`hil.bench.seeds` (the paper figures, and the command that
runs the UAV comparison) and :mod:`hil.bench.seeds_uav` (which runs the rig's emulators with the
same GNSS figures) need not import each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

SCHULER_RADPS = math.sqrt(9.81 / 6_372_000.0)

# The seed-000 GNSS error model (digest §1), as this reproduction reconstructs it: white noise
# sampled at 1 s, σ 20 m on coordinates and 0.2 m/s on velocity, plus a slow geometry/DOP
# component, a 5 m sine whose period is 2.5 Schuler periods (the paper says 2–3). The UAV
# comparison (hil.bench.seeds_uav) runs the rig's GNSS emulator with these same figures.
SEED_GNSS_RATE_HZ = 1.0
SEED_GNSS_POS_SIGMA_M = 20.0
SEED_GNSS_VEL_SIGMA_MPS = 0.2
SEED_GNSS_SLOW_AMPLITUDE_M = 5.0
SEED_GNSS_SLOW_PERIOD_S = 2.5 * 2 * math.pi / SCHULER_RADPS


@dataclass
class Report:
    """The rows, notes and plotted series every experiment adds to, in the order it runs."""

    rows: list[tuple[str, str, str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    series: dict[str, Any] = field(default_factory=dict)

    def add(self, seed: str, figure: str, paper: str, ours: str) -> None:
        self.rows.append((seed, figure, paper, ours))

    def markdown(self) -> str:
        out = ["| seed | figure | paper | rig reproduction |", "| --- | --- | --- | --- |"]
        out += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in self.rows]
        out += ["", "Conditions and differences:", ""]
        out += [f"- {n}" for n in self.notes]
        return "\n".join(out)
