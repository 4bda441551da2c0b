"""``hil campaign ...``: the forms of the command; ``hil.cli`` hands it everything after ``campaign``.

    hil campaign SPEC.toml [--out DIR]                       a campaign from its spec file
    hil campaign sim --scenario S --runs N [--duration D] --out DIR
    hil campaign rerun FILES_OR_DIRS... --out DIR [--estimators a,b] [--no-verify]
    hil campaign builtin NAME [--runs N] [--out DIR]          seed004, uav_nees (--list)
    hil campaign report DIR [--compare BEFORE_DIR] [--out REPORT_DIR]
    hil campaign repro DIR --run N [--record F.mcap]         one run alone, checked against DIR

Every form that runs takes ``--scheduler tcp://HOST:PORT`` (an existing Dask cluster; default: a
local one with a worker per core, or ``--workers N``). Errors a user can fix raise
:class:`UsageError` (one line, exit 2 in ``hil.cli``).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from hil.campaign.spec import DEFAULT_CONFIG, RECORDED, SpecError, spec_from_dict
from hil.runtime.argtypes import OneLineParser, duration_s, positive_float, seconds

FORMS = ("sim", "rerun", "builtin", "report", "repro")


class UsageError(Exception):
    """A campaign command the user can fix; one line."""


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return v


def _run_options(p: argparse.ArgumentParser, out_required: bool) -> None:
    p.add_argument("--out", type=Path, required=out_required, default=None, help="the campaign's directory")
    p.add_argument(
        "--scheduler",
        default=os.environ.get("HIL_DASK_SCHEDULER") or None,
        help="tcp://HOST:PORT of a Dask scheduler (default: $HIL_DASK_SCHEDULER, else a local cluster)",
    )
    p.add_argument(
        "--workers", type=_positive_int, default=None, help="local cluster size (default: one per core)"
    )
    p.add_argument(
        "--connect-timeout", type=positive_float, default=10.0, help="seconds to reach the scheduler"
    )
    p.add_argument("--keep-recordings", default=None, help="keep every run's MCAP in this (shared) directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _overrides(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=_positive_int, default=None, help="replicates (overrides the spec's)")
    p.add_argument("--duration", type=duration_s, default=None, help="seconds per run (overrides)")
    p.add_argument(
        "--settle", type=seconds, default=None, help="statistics skip the first SETTLE s (overrides)"
    )


def _estimators(text: str | None) -> list[str] | None:
    """``--estimators``: None when not given (the spec's default), else its names, each once."""
    from hil.estimators.names import estimator_names

    if text is None:
        return None
    try:
        return estimator_names(text)
    except ValueError as err:
        raise UsageError(str(err)) from None


def _execute(doc: dict[str, Any], base: Path, a: argparse.Namespace, default_name: str) -> int:
    """Check the spec, run it, print what happened; exit 0 only if every run has a result."""
    from hil.campaign.driver import DriverOptions, run_campaign

    if getattr(a, "runs", None) is not None:
        doc["runs"] = a.runs
    if getattr(a, "duration", None) is not None:
        doc["duration_s"] = a.duration
    if getattr(a, "settle", None) is not None:
        doc["settle_s"] = a.settle
    if a.keep_recordings is not None:
        doc["keep_recordings"] = a.keep_recordings
    spec = spec_from_dict(doc, base, default_name)
    out = a.out or Path("campaigns") / spec.name
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: is a file, not a directory; name a directory for the campaign")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(
            f"--out {out}: cannot make the directory ({err.strerror or err}); name another"
        ) from None
    if a.workers is not None and a.scheduler is not None:
        print(
            "hil campaign: note: --workers sizes a local cluster; ignored with --scheduler", file=sys.stderr
        )
    opts = DriverOptions(
        out_dir=out,
        scheduler=a.scheduler,
        workers=a.workers,
        connect_timeout_s=a.connect_timeout,
        progress=False if a.quiet else None,
    )
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        res = run_campaign(spec, opts)
    except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (kill, timeout, a batch system's stop)
        return _stopped(spec.name, out, isinstance(stop, _Terminated))
    finally:
        signal.signal(signal.SIGTERM, previous)
    return _summary(spec.name, out, res)


class _Terminated(KeyboardInterrupt):
    """SIGTERM taken as Ctrl-C is: the driver closes the cluster and writes the table on its way out."""


def _terminate(_signum: int, _frame: Any) -> None:
    raise _Terminated


def _stopped(name: str, out: Path, terminated: bool) -> int:
    """Every result that came back is in the journal already; say so, and how to go on."""
    from hil.campaign.results import current_keys, read_results

    keys = set(current_keys(out) or ())
    done = len(read_results(out).done_keys() & keys)
    print(
        f"hil campaign {name}: stopped ({'SIGTERM' if terminated else 'interrupted'}): {done} of "
        f"{len(keys)} runs have a result in {out}; the same command runs the rest",
        file=sys.stderr,
    )
    return 143 if terminated else 130


def _summary(name: str, out: Path, res: Any) -> int:
    ran = res.ran
    rate = f" ({60 * ran / res.wall_s:.1f} runs/min)" if ran and res.wall_s > 0 else ""
    where = f" on {res.cluster}" if res.cluster else ""
    print(
        f"hil campaign {name}: {res.total} runs, {res.skipped} already done, {ran} run{where} "
        f"in {res.wall_s:.1f} s{rate}"
    )
    if ran:
        print("  " + ", ".join(f"{k} {v}" for k, v in sorted(res.counts.items())))
    if res.torn_lines:
        print(f"  note: {res.torn_lines} torn line(s) in results.jsonl skipped (a campaign killed mid-write)")
    for run, status, error in res.failures[:20]:
        print(f"  {status.upper()} {run.label()}: {error}")
        print(f"    reproduce: hil campaign repro {out} --run {run.index}")
    if len(res.failures) > 20:
        print(f"  ... and {len(res.failures) - 20} more (hil campaign report {out})")
    table = res.table or out / "results.jsonl"
    print(f"results: {table}" + ("" if res.table else " (no pyarrow: the journal is the table)"))
    print(f"report:  hil campaign report {out}")
    return 1 if res.failures else 0


def _spec_form(argv: list[str]) -> int:
    p = OneLineParser(prog="hil campaign", description="run a campaign from its spec file")
    p.add_argument("spec", type=Path, help="campaign spec (TOML; docs/campaigns.md)")
    _overrides(p)
    _run_options(p, out_required=False)
    a = p.parse_args(argv)
    try:
        doc = tomllib.loads(a.spec.read_text(encoding="utf-8"))
    except OSError as err:
        raise SpecError(f"spec: cannot read {a.spec}: {err.strerror or err}") from None
    except tomllib.TOMLDecodeError as err:
        raise SpecError(f"spec: {a.spec} is not valid TOML: {err}") from None
    return _execute(doc, a.spec.resolve().parent, a, a.spec.stem)


def _sim_form(argv: list[str]) -> int:
    p = OneLineParser(prog="hil campaign sim", description="N runs of hil sim with derived seeds")
    p.add_argument(
        "--scenario", action="append", required=True, help="built-in name or TOML path (repeatable)"
    )
    p.add_argument("--runs", type=_positive_int, required=True, help="runs per scenario")
    p.add_argument(
        "--duration", type=duration_s, default=None, help="seconds per run (default: the scenario's)"
    )
    p.add_argument("--seed", type=int, default=0, help="campaign seed: each run's seed derives from it")
    p.add_argument("--estimators", default=None, help="comma-separated (default: the registry's)")
    p.add_argument("--settle", type=seconds, default=0.0, help="statistics skip the first SETTLE seconds")
    p.add_argument("--name", default=None, help="campaign name (default: sim-<scenario>)")
    _run_options(p, out_required=True)
    a = p.parse_args(argv)
    cfg: dict[str, Any] = {} if a.estimators is None else {"estimators": _estimators(a.estimators)}
    doc: dict[str, Any] = {
        "name": a.name or "sim-" + "-".join(Path(s).stem for s in a.scenario),
        "seed": a.seed,
        "runs": a.runs,
        "settle_s": a.settle,
        "configs": {DEFAULT_CONFIG: cfg},
        "sim": {"scenarios": a.scenario},
    }
    if a.duration is not None:
        doc["duration_s"] = a.duration
    a.runs = a.duration = a.settle = None  # already in the document
    return _execute(doc, Path.cwd(), a, "sim")


def _rerun_form(argv: list[str]) -> int:
    p = OneLineParser(prog="hil campaign rerun", description="rerun recordings through the fusion")
    p.add_argument("recordings", nargs="+", help="MCAP files or directories holding them")
    p.add_argument(
        "--estimators", default=None, help="rerun with these estimators instead of the recorded ones"
    )
    p.add_argument("--no-verify", action="store_true", help="do not compare with the recorded outputs")
    p.add_argument("--name", default="rerun", help="campaign name")
    _run_options(p, out_required=True)
    a = p.parse_args(argv)
    doc: dict[str, Any] = {"name": a.name, "rerun": {"recordings": a.recordings, "verify": not a.no_verify}}
    est = _estimators(a.estimators)
    if est is not None:
        doc["configs"] = {"changed": {"estimators": est}}
        doc["rerun"]["configs"] = ["changed"]
    else:
        doc["rerun"]["configs"] = [RECORDED]
    return _execute(doc, Path.cwd(), a, "rerun")


def builtin_names() -> list[str]:
    root = resources.files("hil") / "campaigns"
    return sorted(
        p.name[: -len(".campaign.toml")] for p in root.iterdir() if p.name.endswith(".campaign.toml")
    )


def _builtin_form(argv: list[str]) -> int:
    p = OneLineParser(prog="hil campaign builtin", description="a campaign shipped with hil")
    p.add_argument("name", nargs="?", help=f"one of: {', '.join(builtin_names())}")
    p.add_argument("--list", action="store_true", help="list the built-in campaigns")
    _overrides(p)
    _run_options(p, out_required=False)
    a = p.parse_args(argv)
    if a.list or not a.name:
        for n in builtin_names():
            print(n)
        return 0 if a.list else 2
    if a.name not in builtin_names():
        raise UsageError(f"no built-in campaign {a.name!r}; built-ins: {', '.join(builtin_names())}")
    res = resources.files("hil") / "campaigns" / f"{a.name}.campaign.toml"
    with resources.as_file(res) as path:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
        return _execute(doc, path.parent, a, a.name)


def _report_form(argv: list[str]) -> int:
    from hil.campaign.report import build_campaign_report

    p = OneLineParser(prog="hil campaign report", description="the HTML report of a campaign")
    p.add_argument("dir", type=Path, help="the campaign's directory")
    p.add_argument(
        "--compare", type=Path, default=None, help="another campaign (before a change): per-run differences"
    )
    p.add_argument("--out", type=Path, default=None, help="report directory (default: DIR/report)")
    a = p.parse_args(argv)
    try:
        rep = build_campaign_report(a.dir, a.out, a.compare)
    except FileNotFoundError as err:
        raise UsageError(str(err)) from None
    for n in rep.notes:
        print(f"hil campaign report: note: {n}", file=sys.stderr)
    print(f"hil campaign report: {rep.html_path} ({len(rep.pngs)} figures)")
    return 0


def _repro_form(argv: list[str]) -> int:
    from hil.campaign.repro import reproduce

    p = OneLineParser(prog="hil campaign repro", description="one run of a campaign, alone")
    p.add_argument("dir", type=Path, help="the campaign's directory")
    p.add_argument("--run", type=int, required=True, help="the run's index (the report names it)")
    p.add_argument("--record", type=Path, default=None, help="MCAP path (default: DIR/repro/run-N.mcap)")
    a = p.parse_args(argv)
    rc, lines = reproduce(a.dir, a.run, a.record)
    print("\n".join(lines))
    return rc


def main(argv: list[str]) -> int:
    """Dispatch on the first word; SpecError and CampaignError become UsageError."""
    from hil.campaign.driver import CampaignError

    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.split("\n\n")[1] if __doc__ else "", file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    forms = {
        "sim": _sim_form,
        "rerun": _rerun_form,
        "builtin": _builtin_form,
        "report": _report_form,
        "repro": _repro_form,
    }
    try:
        return forms.get(argv[0], _spec_form)(argv[1:] if argv[0] in forms else argv)
    except (SpecError, CampaignError) as err:
        raise UsageError(str(err)) from None
