"""``--estimators``: one parser for hil sim, hil up and hil campaign."""

from __future__ import annotations

import pytest

from hil.estimators.names import estimator_names
from hil.nodes.fusion import FusionOptions


def test_names_may_have_spaces_around_them() -> None:
    assert estimator_names(" ekf15 , kfvel") == ["ekf15", "kfvel"]
    assert estimator_names("ins") == ["ins"]


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("", "names no estimator"),
        (",", "names no estimator"),
        (" , ", "names no estimator"),
        ("ekf15,,kfvel", "has an empty name"),
        ("ekf15,", "has an empty name"),
        ("ekf15,ekf15", "names ekf15 more than once"),
        ("ekf15, kfvel ,ekf15", "names ekf15 more than once"),
    ],
)
def test_an_empty_list_or_a_repeated_name_is_refused(text: str, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        estimator_names(text)


def test_the_fusion_refuses_a_repeated_estimator_however_it_is_configured() -> None:
    """hil up's services are configured by options, not by the command line."""
    with pytest.raises(ValueError, match="named more than once"):
        FusionOptions(estimators=["ekf15", "ekf15"])


@pytest.mark.parametrize(
    ("value", "why"), [("ekf15,ekf15", "names ekf15 more than once"), ("", "names no estimator")]
)
def test_hil_campaign_refuses_them_in_one_line_exit_2(
    value: str, why: str, tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:  # type: ignore[no-untyped-def]
    from hil.cli import main

    out = tmp_path / "c"
    argv = [
        "campaign",
        "sim",
        "--scenario",
        "static",
        "--runs",
        "1",
        "--out",
        str(out),
        "--estimators",
        value,
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and why in err[0], err
    assert not out.exists()  # refused before the campaign started


@pytest.mark.parametrize("where", ["file", "/proc/x"])
def test_hil_campaign_out_that_cannot_be_a_directory_is_one_line(
    where: str, tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:  # type: ignore[no-untyped-def]
    """A regular file gave a raw FileExistsError, /proc/x a raw FileNotFoundError."""
    from hil.cli import main

    out = tmp_path / "f" if where == "file" else where
    if where == "file":
        out.write_text("x")  # type: ignore[union-attr]
    assert main(["campaign", "sim", "--scenario", "static", "--runs", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"hil: --out {out}: "), err
    assert "Errno" not in err[0] or "cannot make the directory" in err[0]
