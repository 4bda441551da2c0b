"""A campaign's runs: every one derived from the spec alone, each a small picklable task.

Seeds. Replicate ``k`` of a campaign with seed ``S`` runs its scenario with the seed
``SeedSequence(S, spawn_key=(k,))`` draws (32 bits): the same for every scenario, fault set and
configuration of that replicate. So configurations and fault sets are compared on the same
sensor noise, run for run (common random numbers: a paired comparison needs far fewer runs than
two independent samples), and adding replicates (``runs`` 200 -> 400) keeps the first 200 as
they were. The run index enumerates replicates outermost for the same reason.

A run's ``key`` is a hash of everything that defines it (scenario text with its seed, duration,
configuration, faults, recording, statistics window), never of its index or the campaign's
name: a resumed campaign skips exactly the runs whose definition it already has results for,
and ``hil campaign repro`` can tell when a spec changed under a stored result.
"""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.campaign.spec import RECORDED, CampaignSpec, FaultSet, SpecError
from hil.nav.scenario import ScenarioError, dump_toml, load_scenario, parse_scenario

SIM, RERUN = "sim", "rerun"
_SPLIT_PART = re.compile(r"_\d{4}\.mcap$")  # a split recording's later part: read with its first


@dataclass(frozen=True)
class RunSpec:
    """One task: a ``hil sim`` run and its statistics, or a fusion rerun of one recording."""

    index: int
    key: str
    kind: str  # SIM or RERUN
    campaign: str
    replicate: int
    scenario: str  # the scenario's name (the recording's, for a rerun: filled by the worker)
    seed: int  # the scenario seed (-1 for a rerun until the worker reads it)
    duration_s: float | None
    config: str
    estimators: tuple[str, ...]  # empty for a rerun as recorded: the recording's own
    lag_s: float
    output_every: int
    faults: str
    settle_s: float
    scenario_toml: str = ""  # SIM: the exact text run, seed and faults applied
    recording: str = ""  # RERUN: the file
    verify: bool = False
    keep_dir: str = ""  # SIM: keep the MCAP here (a path every worker shares)

    def label(self) -> str:
        what = self.recording if self.kind == RERUN else f"{self.scenario} seed {self.seed}"
        return f"run {self.index} ({what}, config {self.config}, faults {self.faults})"


def replicate_seed(campaign_seed: int, replicate: int) -> int:
    """The scenario seed of replicate ``k``: independent streams from one campaign seed."""
    ss = np.random.SeedSequence(campaign_seed, spawn_key=(replicate,))
    return int(ss.generate_state(1, np.uint32)[0])


def _key(**definition: Any) -> str:
    blob = json.dumps(definition, sort_keys=True, separators=(",", ":"), default=list)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def scenario_doc(ref: str, where: str) -> tuple[str, dict[str, Any]]:
    """A scenario's name and parsed document, or a SpecError naming ``where``."""
    try:
        base = load_scenario(ref)
    except ScenarioError as err:
        raise SpecError(f"{where}: {err}") from None
    doc = tomllib.loads(base.source_text)
    doc.setdefault("name", base.name)
    return base.name, doc


def run_scenario_text(doc: dict[str, Any], seed: int, faults: FaultSet) -> str:
    """The scenario text one run runs: the document with its seed and the fault set's events."""
    d = dict(doc)
    d["seed"] = int(seed)
    events = [] if faults.drop_scenario_events else list(d.get("event", []))
    events += [dict(e) for e in faults.events]
    d.pop("event", None)
    if events:
        d["event"] = events
    what = f"seed {seed}" + (
        f", fault set {faults.name}" if faults.events or faults.drop_scenario_events else ""
    )
    return dump_toml(d, header=f"{d['name']} for a campaign run: {what}")


def _check_faults(doc: dict[str, Any], faults: FaultSet, where: str) -> None:
    try:
        parse_scenario(run_scenario_text(doc, 0, faults), doc["name"])
    except ScenarioError as err:
        raise SpecError(f"faults.{faults.name}.events with {where}: {err}") from None


def sim_runs(spec: CampaignSpec, first_index: int = 0) -> list[RunSpec]:
    """Every ``hil sim`` run: replicate outermost, then scenario, fault set, configuration."""
    part = spec.sim
    if part is None:
        return []
    docs = [scenario_doc(ref, f"sim.scenarios[{i}]") for i, ref in enumerate(part.scenarios)]
    for (_name, doc), ref in zip(docs, part.scenarios, strict=True):
        for f in part.faults:
            _check_faults(doc, spec.faults[f], f"scenario {ref!r}")
    out: list[RunSpec] = []
    for k in range(spec.runs):
        seed = replicate_seed(spec.seed, k)
        for name, doc in docs:
            for f in part.faults:
                text = run_scenario_text(doc, seed, spec.faults[f])
                for c in part.configs:
                    cfg = spec.configs[c]
                    key = _key(
                        kind=SIM,
                        scenario=text,
                        duration_s=spec.duration_s,
                        estimators=cfg.estimators,
                        lag_s=cfg.lag_s,
                        output_every=cfg.output_every,
                        settle_s=spec.settle_s,
                    )
                    out.append(
                        RunSpec(
                            index=first_index + len(out),
                            key=key,
                            kind=SIM,
                            campaign=spec.name,
                            replicate=k,
                            scenario=name,
                            seed=seed,
                            duration_s=spec.duration_s,
                            config=c,
                            estimators=cfg.estimators,
                            lag_s=cfg.lag_s,
                            output_every=cfg.output_every,
                            faults=f,
                            settle_s=spec.settle_s,
                            scenario_toml=text,
                            keep_dir=spec.keep_recordings,
                        )
                    )
    return out


def recording_files(entries: tuple[str, ...]) -> list[Path]:
    """The recordings named: files as given, directories searched for ``*.mcap`` (sorted; a split
    recording's later parts are read with its first, so they are not runs of their own)."""
    out: list[Path] = []
    for i, e in enumerate(entries):
        p = Path(e)
        if p.is_dir():
            found = sorted(q for q in p.rglob("*.mcap") if q.is_file() and not _SPLIT_PART.search(q.name))
            if not found:
                raise SpecError(f"rerun.recordings[{i}]: {p} holds no *.mcap file")
            out += found
        elif p.is_file():
            out.append(p)
        else:
            raise SpecError(f"rerun.recordings[{i}]: no such file or directory: {p}")
    seen: set[Path] = set()
    return [p for p in out if not (p in seen or seen.add(p))]  # type: ignore[func-returns-value]


def rerun_runs(spec: CampaignSpec, first_index: int = 0) -> list[RunSpec]:
    """Every rerun: each recording under each configuration (``recorded``: its own)."""
    part = spec.rerun
    if part is None:
        return []
    out: list[RunSpec] = []
    for j, path in enumerate(recording_files(part.recordings)):
        size = path.stat().st_size
        for c in part.configs:
            cfg = None if c == RECORDED else spec.configs[c]
            verify = part.verify and cfg is None  # a changed configuration cannot reproduce the file
            est = () if cfg is None else cfg.estimators
            every = 0 if cfg is None else cfg.output_every
            key = _key(
                kind=RERUN,
                recording=str(path),
                size=size,
                estimators=est,
                output_every=every,
                verify=verify,
                settle_s=spec.settle_s,
            )
            out.append(
                RunSpec(
                    index=first_index + len(out),
                    key=key,
                    kind=RERUN,
                    campaign=spec.name,
                    replicate=j,
                    scenario="",
                    seed=-1,
                    duration_s=None,
                    config=c,
                    estimators=est,
                    lag_s=0.0,
                    output_every=every,
                    faults="",
                    settle_s=spec.settle_s,
                    recording=str(path),
                    verify=verify,
                )
            )
    return out


def derive_runs(spec: CampaignSpec) -> list[RunSpec]:
    """All runs of a spec, sim runs first; scenarios, fault sets and recordings are checked here
    (on the client) so a bad one is refused before any task is sent."""
    sims = sim_runs(spec)
    runs = sims + rerun_runs(spec, first_index=len(sims))
    keys = [r.key for r in runs]
    if len(set(keys)) != len(keys):
        dup = next(r for r in runs if keys.count(r.key) > 1)
        raise SpecError(f"spec: {dup.label()} is defined twice (two identical configurations or scenarios)")
    return runs


def run_dict(run: RunSpec) -> dict[str, Any]:
    """The run's definition as plain data (tests, debugging)."""
    return asdict(run)
