"""A campaign spec (TOML): what to run, refused whole and in one line before any task is sent.

A campaign is ``runs`` replicates of every scenario x fault set x fusion configuration for
``hil sim`` (section ``[sim]``), and/or every recording x configuration for a fusion rerun
(section ``[rerun]``). The format, with an example, is in ``docs/campaigns.md``.

Every problem is a :class:`SpecError` (a ``ValueError``) whose message starts with the key it is
about (``configs.fast.estimators: unknown estimator 'ekf16' ...``), so the CLI shows one line and
exits 2 -- a typo found after 200 tasks went out would waste a cluster's afternoon.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.estimators.registry import DEFAULT_ESTIMATORS, ESTIMATORS
from hil.fusion.core import FREE_INS
from hil.nav.scenario import dump_toml
from hil.nodes.fusion import DEFAULT_LAG_S, DEFAULT_OUTPUT_EVERY

RECORDED = "recorded"  # the rerun configuration a recording says it ran with
DEFAULT_CONFIG = "default"
NO_FAULTS = "none"
MAX_RUNS = 1_000_000

_TOP_KEYS = {
    "name",
    "description",
    "seed",
    "runs",
    "duration_s",
    "settle_s",
    "keep_recordings",
    "configs",
    "faults",
    "sim",
    "rerun",
}
_CONFIG_KEYS = {"estimators", "lag_s", "output_every"}
_FAULT_KEYS = {"events", "drop_scenario_events"}
_SIM_KEYS = {"scenarios", "configs", "faults"}
_RERUN_KEYS = {"recordings", "configs", "verify"}


class SpecError(ValueError):
    """A campaign spec that cannot be run; the message names the key first."""


@dataclass(frozen=True)
class FusionSetup:
    """One fusion configuration: which estimators, the horizon lag, the output decimation."""

    name: str
    estimators: tuple[str, ...] = DEFAULT_ESTIMATORS
    lag_s: float = DEFAULT_LAG_S
    output_every: int = DEFAULT_OUTPUT_EVERY


@dataclass(frozen=True)
class FaultSet:
    """Scenario events (``[[event]]`` tables, the scenario format's) added to every scenario."""

    name: str
    events: tuple[Mapping[str, Any], ...] = ()
    drop_scenario_events: bool = False


@dataclass(frozen=True)
class SimPart:
    scenarios: tuple[str, ...]  # built-in names or absolute paths
    configs: tuple[str, ...]
    faults: tuple[str, ...]


@dataclass(frozen=True)
class RerunPart:
    recordings: tuple[str, ...]  # absolute files or directories
    configs: tuple[str, ...]  # RECORDED or names of [configs.*]
    verify: bool = True


@dataclass(frozen=True)
class CampaignSpec:
    name: str
    seed: int = 0
    runs: int = 1
    duration_s: float | None = None  # None: each scenario's own duration
    settle_s: float = 0.0  # statistics skip the first settle_s seconds (convergence does not)
    keep_recordings: str = ""  # a directory every worker can write; "" deletes each MCAP
    description: str = ""
    configs: Mapping[str, FusionSetup] = field(default_factory=dict)
    faults: Mapping[str, FaultSet] = field(default_factory=dict)
    sim: SimPart | None = None
    rerun: RerunPart | None = None

    def to_toml(self) -> str:
        """The spec as a TOML file that parses back to this spec (``DIR/campaign.toml``)."""
        doc: dict[str, Any] = {"name": self.name, "seed": self.seed, "runs": self.runs}
        if self.description:
            doc["description"] = self.description
        if self.duration_s is not None:
            doc["duration_s"] = self.duration_s
        doc["settle_s"] = self.settle_s
        if self.keep_recordings:
            doc["keep_recordings"] = self.keep_recordings
        doc["configs"] = {
            c.name: {"estimators": list(c.estimators), "lag_s": c.lag_s, "output_every": c.output_every}
            for c in self.configs.values()
        }
        if self.faults:
            doc["faults"] = {
                f.name: {
                    "events": [dict(e) for e in f.events],
                    "drop_scenario_events": f.drop_scenario_events,
                }
                for f in self.faults.values()
            }
        if self.sim is not None:
            s = self.sim
            doc["sim"] = {
                "scenarios": list(s.scenarios),
                "configs": list(s.configs),
                "faults": list(s.faults),
            }
        if self.rerun is not None:
            r = self.rerun
            doc["rerun"] = {"recordings": list(r.recordings), "configs": list(r.configs), "verify": r.verify}
        return dump_toml(
            doc, header=f"hil campaign {self.name}: the spec as run (hil campaign THIS_FILE resumes)"
        )


# ---------------------------------------------------------------------------------------------
# value checks: each names its key


def _keys(where: str, table: Any, allowed: set[str]) -> Mapping[str, Any]:
    if not isinstance(table, Mapping):
        raise SpecError(f"{where}: must be a table, got {table!r}")
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise SpecError(
            f"{where + '.' if where else ''}{unknown[0]}: unknown key; allowed: {sorted(allowed)}"
        )
    return table


def _int(where: str, v: Any, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise SpecError(f"{where}: must be an integer in [{lo}, {hi}], got {v!r}")
    return v


def _float(
    where: str, v: Any, *, lo: float = -math.inf, hi: float = math.inf, open_lo: bool = False
) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise SpecError(f"{where}: must be a finite number, got {v!r}")
    if (v <= lo if open_lo else v < lo) or v > hi:
        rel = ">" if open_lo else ">="
        raise SpecError(
            f"{where}: must be {rel} {lo:g}" + (f" and <= {hi:g}" if hi < math.inf else "") + f", got {v!r}"
        )
    return float(v)


def _str(where: str, v: Any) -> str:
    if not isinstance(v, str):
        raise SpecError(f"{where}: must be a string, got {v!r}")
    return v


def _strs(where: str, v: Any, *, nonempty: bool = True) -> tuple[str, ...]:
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise SpecError(f"{where}: must be a list of strings, got {v!r}")
    if nonempty and not v:
        raise SpecError(f"{where}: must not be empty")
    if len(set(v)) != len(v):
        raise SpecError(f"{where}: lists {sorted({x for x in v if v.count(x) > 1})} twice")
    return tuple(v)


def _name(where: str, v: str) -> str:
    if not v or not all(c.isalnum() or c in "_-." for c in v):
        raise SpecError(f"{where}: a name must be letters, digits, '_', '-' or '.', got {v!r}")
    return v


def _config(name: str, raw: Any) -> FusionSetup:
    where = f"configs.{_name('configs', name)}"
    if name == RECORDED:
        raise SpecError(f"{where}: {RECORDED!r} is reserved (a rerun with the recording's own configuration)")
    t = _keys(where, raw, _CONFIG_KEYS)
    est = _strs(f"{where}.estimators", t.get("estimators", list(DEFAULT_ESTIMATORS)))
    unknown = [e for e in est if e not in ESTIMATORS and e != FREE_INS]
    if unknown:
        raise SpecError(
            f"{where}.estimators: unknown estimator {unknown[0]!r}; known: {sorted(ESTIMATORS)} "
            f"(and {FREE_INS!r}, the free INS alone)"
        )
    lag = _float(f"{where}.lag_s", t.get("lag_s", DEFAULT_LAG_S), lo=0.0, hi=60.0)
    every = _int(f"{where}.output_every", t.get("output_every", DEFAULT_OUTPUT_EVERY), 1, 10**6)
    return FusionSetup(name, est, lag, every)


def _fault_set(name: str, raw: Any) -> FaultSet:
    where = f"faults.{_name('faults', name)}"
    t = _keys(where, raw, _FAULT_KEYS)
    events = t.get("events", [])
    if not isinstance(events, list) or not all(isinstance(e, Mapping) for e in events):
        raise SpecError(f"{where}.events: must be a list of tables (the scenario's [[event]] format)")
    drop = t.get("drop_scenario_events", False)
    if not isinstance(drop, bool):
        raise SpecError(f"{where}.drop_scenario_events: must be true or false, got {drop!r}")
    return FaultSet(name, tuple(dict(e) for e in events), drop)


def _table(where: str, v: Any) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise SpecError(f"{where}: must be a table, got {v!r}")
    return v


def _abs(base: Path, text: str) -> str:
    p = Path(text).expanduser()
    return str(p if p.is_absolute() else (base / p).resolve())


def _scenario_ref(base: Path, text: str) -> str:
    """A scenario as ``load_scenario`` takes it: a bare name stays a built-in, a path becomes absolute."""
    return text if "/" not in text and not text.endswith(".toml") else _abs(base, text)


def _pick(where: str, v: Any, known: Mapping[str, Any], extra: tuple[str, ...] = ()) -> tuple[str, ...]:
    names = _strs(where, v)
    for n in names:
        if n not in known and n not in extra:
            raise SpecError(f"{where}: {n!r} is not defined; defined: {sorted([*known, *extra])}")
    return names


def _sim(raw: Any, base: Path, configs: Mapping[str, FusionSetup], faults: Mapping[str, FaultSet]) -> SimPart:
    t = _keys("sim", raw, _SIM_KEYS)
    if "scenarios" not in t:
        raise SpecError("sim.scenarios: missing (built-in names or scenario TOML paths)")
    scen = tuple(_scenario_ref(base, s) for s in _strs("sim.scenarios", t["scenarios"]))
    cfg = _pick("sim.configs", t.get("configs", list(configs)), configs)
    flt = _pick("sim.faults", t.get("faults", list(faults)), faults)
    return SimPart(scen, cfg, flt)


def _rerun(raw: Any, base: Path, configs: Mapping[str, FusionSetup]) -> RerunPart:
    t = _keys("rerun", raw, _RERUN_KEYS)
    if "recordings" not in t:
        raise SpecError("rerun.recordings: missing (MCAP files or directories holding them)")
    recs = tuple(_abs(base, s) for s in _strs("rerun.recordings", t["recordings"]))
    cfg = _pick("rerun.configs", t.get("configs", [RECORDED]), configs, (RECORDED,))
    verify = t.get("verify", True)
    if not isinstance(verify, bool):
        raise SpecError(f"rerun.verify: must be true or false, got {verify!r}")
    return RerunPart(recs, cfg, verify)


def parse_spec(text: str, base_dir: Path, default_name: str = "campaign") -> CampaignSpec:
    """Check and build a spec from TOML text; relative paths are taken from ``base_dir``."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SpecError(f"spec: not valid TOML: {err}") from None
    return spec_from_dict(doc, base_dir, default_name)


def spec_from_dict(doc: Mapping[str, Any], base_dir: Path, default_name: str = "campaign") -> CampaignSpec:
    """The checks of :func:`parse_spec` on an already parsed document (the one-line forms)."""
    _keys("", doc, _TOP_KEYS)
    name = _name("name", _str("name", doc.get("name", default_name)))
    seed = _int("seed", doc.get("seed", 0), 0, 2**63 - 1)
    runs = _int("runs", doc.get("runs", 1), 1, MAX_RUNS)
    duration = doc.get("duration_s")
    duration_s = None if duration is None else _float("duration_s", duration, lo=0.0, open_lo=True)
    settle = _float("settle_s", doc.get("settle_s", 0.0), lo=0.0)
    if duration_s is not None and settle >= duration_s:
        raise SpecError(f"settle_s: {settle:g} s leaves nothing of a {duration_s:g} s run to judge")
    keep = _str("keep_recordings", doc.get("keep_recordings", ""))
    raw_cfg = _table("configs", doc.get("configs", {DEFAULT_CONFIG: {}}))
    if not raw_cfg:
        raise SpecError(
            "configs: must define at least one configuration (or be left out: the registry's default)"
        )
    configs = {n: _config(n, c) for n, c in raw_cfg.items()}
    raw_f = _table("faults", doc.get("faults", {NO_FAULTS: {}}))
    faults = {n: _fault_set(n, f) for n, f in raw_f.items()} or {NO_FAULTS: FaultSet(NO_FAULTS)}
    sim = _sim(doc["sim"], base_dir, configs, faults) if "sim" in doc else None
    rerun = _rerun(doc["rerun"], base_dir, configs) if "rerun" in doc else None
    if sim is None and rerun is None:
        raise SpecError("spec: nothing to run: give a [sim] section, a [rerun] section, or both")
    return CampaignSpec(
        name=name,
        seed=seed,
        runs=runs,
        duration_s=duration_s,
        settle_s=settle,
        keep_recordings=str(Path(keep).expanduser().resolve()) if keep else "",
        description=_str("description", doc.get("description", "")),
        configs=configs,
        faults=faults,
        sim=sim,
        rerun=rerun,
    )


def load_spec(path: str | Path) -> CampaignSpec:
    """A spec file; its relative paths are relative to the file's directory."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        raise SpecError(f"spec: cannot read {p}: {err.strerror or err}") from None
    return parse_spec(text, p.resolve().parent, p.stem)
