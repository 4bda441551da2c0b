"""``hil campaign repro DIR --run N``: one run of a campaign, alone, on this machine.

The run is derived again from ``DIR/campaign.toml`` (the spec as the campaign ran it), so it
needs nothing but the directory; it keeps the run's MCAP (``hil report``/``hil info`` it) and
its scenario TOML, prints the plain ``hil sim`` command that makes the same recording, and
compares its statistics with the campaign's stored row, figure by figure: a run is
deterministic from its spec, so they are identical unless the code or a scenario file changed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hil.campaign.execute import code_fingerprint, execute_run
from hil.campaign.results import SPEC, read_results
from hil.campaign.runs import SIM, derive_runs
from hil.campaign.spec import SpecError, load_spec
from hil.nodes.fusion import DEFAULT_LAG_S, DEFAULT_OUTPUT_EVERY

COMPARED = ("n", "h_rms_m", "h_p95_m", "h_max_m", "h_final_m", "conv_s", "nees_mean", "nees_in_band")


def _stored(campaign_dir: Path, key: str) -> dict[str, dict[str, Any]]:
    return {est: r for (k, est), r in read_results(campaign_dir).latest().items() if k == key}


def reproduce(campaign_dir: str | Path, index: int, record: Path | None = None) -> tuple[int, list[str]]:
    """Exit code (0: every figure identical to the stored one) and the lines to print."""
    d = Path(campaign_dir)
    if not (d / SPEC).is_file():
        raise SpecError(f"{d}: no {SPEC} (not a campaign directory)")
    runs = derive_runs(load_spec(d / SPEC))
    if not 0 <= index < len(runs):
        raise SpecError(f"--run {index}: the campaign has runs 0..{len(runs) - 1}")
    run = runs[index]
    stored = _stored(d, run.key)
    lines = [f"hil campaign repro: {run.label()}"]
    if not stored:
        old = [r for r in read_results(d).table() if r["run"] == index]
        if old:
            lines.append(
                f"note: the stored run {index} has another definition (key {old[0]['key']}, now {run.key}): "
                "the spec or a scenario file changed since; running the run as the spec says now"
            )
    keep = None
    if run.kind == SIM:
        keep = record or d / "repro" / f"run-{index}.mcap"
        scen = keep.with_suffix(".toml")
        keep.parent.mkdir(parents=True, exist_ok=True)
        scen.write_text(run.scenario_toml, encoding="utf-8")
        lines.append(f"scenario: {scen}")
        if run.lag_s == DEFAULT_LAG_S and run.output_every == DEFAULT_OUTPUT_EVERY:
            dur = f" --duration {run.duration_s:g}" if run.duration_s is not None else ""
            lines.append(
                f"the same recording with hil sim: hil sim --scenario {scen}{dur} "
                f"--estimators {','.join(run.estimators)} --record {keep} --rig sim"
            )
    rows = execute_run(run, keep=keep)
    if keep is not None:
        lines.append(f"recording: {keep}")
    return _compare(rows, stored, lines)


def _compare(
    rows: list[dict[str, Any]], stored: dict[str, dict[str, Any]], lines: list[str]
) -> tuple[int, list[str]]:
    rc = 0
    for r in rows:
        est = r["estimator"]
        figures = "  ".join(f"{c}={r.get(c)}" for c in COMPARED if r.get(c) is not None)
        lines.append(f"{est or '-'}: {r['status']}{' ' + r['error'] if r['error'] else ''}  {figures}")
        s = stored.get(est)
        if s is None:
            continue
        diff = [f"{c} {s.get(c)} -> {r.get(c)}" for c in COMPARED if s.get(c) != r.get(c)]
        if diff or s["status"] != r["status"]:
            rc = 1
            code = (
                ""
                if s.get("code") == code_fingerprint()
                else f" (stored with code {s.get('code')}, now {code_fingerprint()})"
            )
            lines.append(
                f"  DIFFERS from the campaign's row{code}: " + "; ".join(diff or [f"status {s['status']}"])
            )
        else:
            lines.append("  identical to the campaign's row")
    if not stored:
        lines.append("(no stored result for this run to compare with)")
    elif any(r["status"] not in ("ok", "mismatch") for r in rows):
        rc = 1
    return rc, lines
