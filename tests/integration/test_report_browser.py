"""The report renders in a real headless browser with no console error and no network request.

GIVEN a report of the golden 4 s ``hil sim`` recording (and of a session with no truth)
WHEN headless Chromium loads it, driven over the DevTools protocol
THEN nothing is logged at warning/error level, nothing throws, nothing is fetched off the page,
every image decodes, and a full-page screenshot is taken (kept next to the report).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.report.browser import check_page, find_chromium
from hil.report.build import build_report
from tests.load import slowdown
from tests.unit.test_report_build import write_session

GOLDEN = Path(__file__).resolve().parents[1] / "replay" / "golden" / "straight_level_4s.mcap"

pytestmark = pytest.mark.skipif(
    find_chromium() is None, reason="needs chromium (Debian: apt-get install -y chromium)"
)


def _check(html: Path) -> None:
    # Chromium's start and a 3000 px screenshot take seconds idle, minutes on a loaded machine
    r = check_page(html, width=1400, height=3000, timeout_s=60.0 * slowdown())
    assert r.errors == [], "\n".join(r.errors)
    assert r.height_px > 1000  # the page laid out its sections
    assert r.screenshot.startswith(b"\x89PNG") and len(r.screenshot) > 20_000
    (html.parent / "screenshot.png").write_bytes(r.screenshot)


def test_golden_report_renders_clean(tmp_path: Path) -> None:
    if not GOLDEN.is_file():
        pytest.skip(f"no golden recording at {GOLDEN}")
    res = build_report(GOLDEN, tmp_path / "golden")
    _check(res.html_path)


def test_degraded_report_renders_clean(tmp_path: Path) -> None:
    p = write_session(tmp_path / "bare.mcap", truth=False, gnss=False, duration_s=4.0)
    res = build_report(p, tmp_path / "bare")
    _check(res.html_path)


def test_checker_sees_console_errors_and_fetches(tmp_path: Path) -> None:
    bad = tmp_path / "bad.html"
    bad.write_text(
        '<html><body><img src="http://example.invalid/x.png">'
        '<script>console.error("boom"); missingFn();</script></body></html>'
    )
    r = check_page(bad, width=400, height=300, timeout_s=60.0 * slowdown())
    text = "\n".join(r.errors)
    assert "console.error: boom" in text
    assert "missingFn" in text
    assert "network request: http://example.invalid/x.png" in text
