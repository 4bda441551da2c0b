"""``hil rerun FILE --core fusion [--verify]``: recompute a core's outputs from recorded inputs.

Fusion: the recorded synchronised inputs, minus those the live fusion journaled as dropped, in
the total order, through a fresh ``FusionCore.process`` -- then every recomputed ``NavSolution``
is compared byte for byte with the recorded one. The first difference is named (topic, seq,
field, both values).
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass
from typing import Any

import msgspec

from hil.fusion.core import FREE_INS, FusionConfig, FusionCore, input_id, input_key
from hil.messages import Event, FusionJournal, GnssFix, ImuSample, NavSolution, RunInfo, encode
from hil.record.mcapio import RecordingError, Session, read_session

FUSION_CONFIG_EVENT = "fusion_config"


def fusion_config_detail(cfg: FusionConfig) -> str:
    return json.dumps(
        {"estimators": list(cfg.estimators), "lag_ns": cfg.lag_ns, "output_every": cfg.output_every}
    )


def fusion_config_from(session: Session) -> FusionConfig:
    for r in session.records:
        if "/event/" in r.topic:
            ev = r.decode()
            assert isinstance(ev, Event)
            if ev.kind == FUSION_CONFIG_EVENT:
                d = json.loads(ev.detail)
                return FusionConfig(
                    estimators=tuple(d["estimators"]),
                    lag_ns=int(d["lag_ns"]),
                    output_every=int(d["output_every"]),
                )
    raise RecordingError(
        f"{session.path}: no '{FUSION_CONFIG_EVENT}' event: the fusion did not run in this session"
    )


def run_info_from(session: Session) -> RunInfo:
    for r in session.records:
        if r.topic.endswith("/run"):
            m = r.decode()
            assert isinstance(m, RunInfo)
            return m
    raise RecordingError(f"{session.path}: no RunInfo (hil/<rig>/run): not a rig session")


@dataclass
class RerunResult:
    recomputed: list[NavSolution]
    recorded: dict[tuple[str, int], bytes]
    inputs_used: int
    inputs_dropped: int
    live_consumed: int = -1  # the last journal's count of inputs the live fusion consumed

    def first_difference(self) -> str | None:
        seen = 0
        for sol in self.recomputed:
            rec = self.recorded.get((sol.estimator, sol.seq))
            if rec is None:
                continue
            seen += 1
            mine = encode(sol)
            if mine != rec:
                theirs = msgspec.json.decode(rec)
                ours = msgspec.json.decode(mine)
                for k in ours:
                    if ours.get(k) != theirs.get(k):
                        return (
                            f"nav/{sol.estimator} seq {sol.seq}: field {k!r} differs: "
                            f"recorded {theirs.get(k)!r}, recomputed {ours.get(k)!r}"
                        )
                return f"nav/{sol.estimator} seq {sol.seq}: payload bytes differ"
        missing = set(self.recorded) - {(s.estimator, s.seq) for s in self.recomputed}
        if missing:
            est, seq = sorted(missing)[0]
            return f"nav/{est} seq {seq}: recorded but not recomputed ({len(missing)} such outputs)"
        if seen == 0:
            return "the recording holds no fusion outputs to compare"
        return None


def rerun_fusion(session: Session, on_progress: Any = None) -> RerunResult:
    from hil.runtime.scenario_io import scenario_for_run

    run = run_info_from(session)
    cfg = fusion_config_from(session)
    produced = {FREE_INS, *cfg.estimators}
    inputs: list[ImuSample | GnssFix] = []
    dropped: Counter[str] = Counter()
    recorded: dict[tuple[str, int], bytes] = {}
    live_consumed = -1
    for r in session.records:
        if "/synced/" in r.topic:
            m = r.decode()
            assert isinstance(m, ImuSample | GnssFix)
            inputs.append(m)
        elif r.topic.endswith("/fusion/journal"):
            j = r.decode()
            assert isinstance(j, FusionJournal)
            live_consumed = max(live_consumed, j.consumed)
            dropped.update(d.split(":", 1)[1] if d.count(":") > 1 else d for d in j.dropped)
        elif "/nav/" in r.topic:
            est = r.topic.rsplit("/", 1)[1]
            if est in produced:  # nav/<dut> and other non-fusion solutions are not the core's
                recorded[(est, r.sequence)] = r.payload
    # an input recorded n times and journaled as dropped d times was consumed max(n - d, 0) times (0 or 1)
    present: Counter[str] = Counter(input_id(m) for m in inputs)
    keep: list[ImuSample | GnssFix] = []
    used: set[str] = set()
    for m in sorted(inputs, key=input_key):
        i = input_id(m)
        if i in used or present[i] - dropped[i] <= 0:
            continue
        used.add(i)
        keep.append(m)
    core = FusionCore.for_scenario(scenario_for_run(run), cfg)
    out: list[NavSolution] = []
    for i, m in enumerate(keep):
        out.extend(core.process(m))
        if on_progress is not None and i % 4096 == 0:
            on_progress(i, len(keep))  # callable(inputs_done, inputs_total)
    return RerunResult(out, recorded, len(keep), sum(dropped.values()), live_consumed)


def rerun(
    path: str, *, core: str = "fusion", verify: bool = False, on_progress: Any = None
) -> tuple[int, list[str]]:
    """Exit code and report lines for ``hil rerun``."""
    session = read_session(path)
    if core == "timesync":
        from hil.record.rerun_timesync import rerun_timesync_report

        return rerun_timesync_report(session, verify)
    if core != "fusion":
        return 2, [f"hil rerun: core {core!r} is not rerunnable (fusion, timesync)"]
    res = rerun_fusion(session, on_progress)
    lines = [
        f"rerun fusion: {res.inputs_used} inputs ({res.inputs_dropped} journaled as dropped), "
        f"{len(res.recomputed)} outputs recomputed, {len(res.recorded)} recorded"
    ]
    if session.truncated:
        lines.append(
            "note: the file is truncated (its recorder did not finish it); "
            "rerun covers it up to its last complete chunk"
        )
    elif res.live_consumed >= 0 and res.live_consumed != res.inputs_used:
        lines.append(
            f"note: the live fusion journaled {res.live_consumed} consumed inputs, the recording holds "
            f"{res.inputs_used} of them: inputs were lost between the fusion and the recorder "
            "(see hil info for seq gaps on synced/*)"
        )
    if not verify:
        return 0, lines
    diff = res.first_difference()
    if diff:
        return 1, [*lines, f"VERIFY FAILED: {diff}"]
    return 0, [*lines, f"VERIFY OK: all {len(res.recorded)} recorded outputs are bit-identical"]
