"""The report's arithmetic on synthetic rows: consistency over runs and pairing two campaigns."""

from __future__ import annotations

from typing import Any

import numpy as np

from hil.campaign.aggregate import consistency, pair, summarise


def _row(
    run: int, key: str, h: list[float], sig: list[float], nees: list[float], **kw: Any
) -> dict[str, Any]:
    r = {
        "run": run,
        "key": key,
        "kind": "sim",
        "scenario": "s",
        "seed": run,
        "faults": "none",
        "config": "a",
        "recording": "",
        "estimator": "ekf15",
        "status": "ok",
        "h_rms_m": float(np.sqrt(np.mean(np.square(h)))),
        "series_dt_s": 1.0,
        "series_h_err_m": h,
        "series_h_sigma_m": sig,
        "series_nees": nees,
    }
    r.update(kw)
    return r


def test_a_consistent_filter_sits_in_its_bands() -> None:
    """Errors drawn with the reported sigma: the mean NEES and RMS/sigma stay in their bands."""
    rng = np.random.default_rng(1)
    runs, n = 200, 50
    sig = np.linspace(5.0, 1.0, n)  # per-axis sigma, N and E equal
    rows = []
    for i in range(runs):
        e = rng.standard_normal((n, 6)) * np.c_[np.repeat(sig[:, None], 3, 1), np.full((n, 3), 0.1)]
        nees = np.sum((e[:, :3] / sig[:, None]) ** 2, 1) + np.sum((e[:, 3:] / 0.1) ** 2, 1)
        rows.append(_row(i, f"k{i}", list(np.hypot(e[:, 0], e[:, 1])), list(np.sqrt(2) * sig), list(nees)))
    c = consistency(rows, settle_s=0.0)
    assert c is not None and c.nees_mean is not None and c.sigma_m is not None
    assert c.inside > 0.85 and c.ratio_inside > 0.85
    assert c.band[0] < 6.0 < c.band[1]
    over = [dict(r, series_nees=[3 * x for x in r["series_nees"]]) for r in rows]  # over-confident
    c3 = consistency(over, settle_s=0.0)
    assert c3 is not None and c3.above > 0.95 and c3.inside < 0.05
    (g,) = summarise(rows, 0.0)
    assert len(g.ok) == runs and g.worst(3)[0]["h_rms_m"] == max(r["h_rms_m"] for r in rows)


def test_pairing_by_key_then_by_situation() -> None:
    before = [_row(i, f"k{i}", [1.0], [1.0], [6.0]) for i in range(4)]
    after = [_row(i, f"k{i}", [1.0 + 0.1 * i], [1.0], [6.0]) for i in range(4)]
    (p,), how = pair(before, after)
    assert how == "key" and len(p.pairs) == 4
    assert np.allclose(p.delta("h_rms_m"), [0.0, 0.1, 0.2, 0.3])
    other = [dict(r, key=r["key"] + "x", config="b") for r in after]  # another configuration
    (p2,), how2 = pair(before, other)
    assert how2 == "situation" and len(p2.pairs) == 4
    failed = [dict(r, status="failed") for r in after]
    assert pair(before, failed)[0] == []
