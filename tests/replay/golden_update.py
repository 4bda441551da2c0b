"""Regenerate the golden replay: ``.venv/bin/python -m tests.replay.golden_update``.

Run this only when a change of the fusion's numbers (or of its inputs: sensors, codec, timesync)
is intended; then commit ``tests/replay/golden/`` together with the change, so the diff of
``expected.json`` is reviewed with it (PX4's change indication, openpilot's ``--update-refs``).

It makes a fresh 4 s ``hil sim`` recording and writes, per estimator, the count and SHA-256 of the
recomputed outputs and the last solution, as ``hil rerun`` computes them from that recording.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

from hil.messages import encode
from hil.record.mcapio import read_session
from hil.record.rerun import rerun_fusion

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
GOLDEN = GOLDEN_DIR / "straight_level_4s.mcap"
EXPECTED = GOLDEN_DIR / "expected.json"
SIM_ARGS = {"scenario": "straight_level", "duration_s": 4.0, "rig": "golden"}


def digest(path: Path) -> dict[str, object]:
    """What the current fusion core computes from the recording's inputs, per estimator."""
    res = rerun_fusion(read_session(path))
    out: dict[str, dict[str, object]] = {}
    hashes: dict[str, Any] = {}  # name -> running sha256
    for sol in res.recomputed:
        h = hashes.setdefault(sol.estimator, hashlib.sha256())
        h.update(encode(sol))
        h.update(b"\n")
        out[sol.estimator] = {
            "outputs": int(out.get(sol.estimator, {}).get("outputs", 0)) + 1,  # type: ignore[call-overload]
            "last_seq": sol.seq,
            "last_pos_ned_m": sol.pos_ned_m,
            "last_vel_ned_mps": sol.vel_ned_mps,
        }
    for name, h in hashes.items():
        out[name]["sha256"] = h.hexdigest()
    return {
        "source": "hil sim --scenario {scenario} --duration 4 --rig {rig}".format(**SIM_ARGS),
        "inputs_used": res.inputs_used,
        "estimators": dict(sorted(out.items())),
    }


def main() -> int:
    from hil.runners.sim import SimOptions, run_sim

    GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
    res = run_sim(
        SimOptions(
            scenario=SIM_ARGS["scenario"], duration_s=SIM_ARGS["duration_s"], record=GOLDEN, rig="golden"
        )
    )
    EXPECTED.write_text(json.dumps(digest(GOLDEN), indent=2) + "\n")
    print(res.summary)
    print(f"wrote {GOLDEN} ({GOLDEN.stat().st_size} B) and {EXPECTED}; review and commit both")
    return 0


if __name__ == "__main__":
    sys.exit(main())
