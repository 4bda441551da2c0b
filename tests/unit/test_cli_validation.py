"""Bad input to ``hil sim``/``hil up`` is one line and exit 2, before anything runs or is written."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.cli import main
from hil.nodes.gnss_emulator import check_wire


@pytest.fixture(autouse=True)
def _nothing_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    """A check that let the command through fails the test before any rig or sim starts."""

    def started(*_args: object, **_kw: object) -> None:
        pytest.fail("the command was not refused: it went on to start the run")

    monkeypatch.setattr("hil.cli._keep_earlier_recording", started)  # hil up: before any process
    monkeypatch.setattr("hil.runners.sim.run_sim", started)


def _refused(capsys: pytest.CaptureFixture[str], tmp_path: Path, *argv: str) -> str:
    """The one line ``hil`` said refusing ``argv`` (exit 2, nothing recorded)."""
    rec = tmp_path / "run.mcap"
    assert main([*argv, "--record", str(rec)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hil: "), err
    assert "Traceback" not in err[0] and "Error: " not in err[0], err  # no exception class name
    assert not rec.exists()
    return err[0]


UNDATED = [
    (["nmea"], ["GGA"], ["no date (add RMC or ZDA)", "no fix type (add GSA)"]),
    (["nmea"], ["GST", "VTG"], ["no date", "no position (add GGA or RMC)", "no altitude (add GGA)"]),
    (["nmea"], ["RMC", "VTG", "GGA", "ZDA"], ["no fix type (add GSA)"]),
    (["nmea"], ["RMC", "GSA", "ZDA"], ["no altitude (add GGA)"]),
    (["ubx"], ["NAV-POSLLH"], ["no date and fix type (add NAV-PVT)"]),
    (["ubx"], ["NAV-POSLLH", "NAV-VELNED", "TIM-TP"], ["(add NAV-PVT)"]),
    (["nmea", "ubx"], ["GGA", "NAV-POSLLH"], ["ubx messages NAV-POSLLH give"]),  # the bridge's is UBX's
]


@pytest.mark.parametrize(("protocols", "messages", "said"), UNDATED, ids=[",".join(m) for _, m, _ in UNDATED])
def test_a_message_set_the_bridge_can_make_no_dated_fix_of_is_refused(
    protocols: list[str], messages: list[str], said: list[str]
) -> None:
    """They were accepted, and every fix was dropped undated or published as "no fix"."""
    with pytest.raises(ValueError, match="give the rig's GNSS bridge no usable fix") as err:
        check_wire(protocols, messages, "GN", 115200)
    for part in said:
        assert part in str(err.value), (part, str(err.value))


@pytest.mark.parametrize(
    ("protocols", "messages"),
    [
        (["nmea"], []),
        (["nmea"], ["GGA", "RMC", "GSA"]),
        (["nmea"], ["GGA", "GSA", "ZDA"]),  # no velocity: the bridge says it is unknown
        (["ubx"], ["NAV-PVT"]),
        (["ubx"], ["NAV-PVT", "TIM-TP"]),
        (["nmea", "ubx"], ["GGA"]),  # UBX's defaults make the fixes
    ],
)
def test_a_message_set_with_a_dated_position_fix_is_taken(protocols: list[str], messages: list[str]) -> None:
    check_wire(protocols, messages, "GN", 115200)


def test_tim_tp_is_ubx_s_and_refused_on_an_nmea_line() -> None:
    """It was taken on every protocol's line, and an NMEA line never sent it."""
    with pytest.raises(ValueError, match=r"\['TIM-TP'\] are not in \['nmea'\]"):
        check_wire(["nmea"], ["GGA", "RMC", "GSA", "TIM-TP"], "GN", 115200)


def test_hil_sim_refuses_an_undated_message_set_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    line = _refused(
        capsys, tmp_path, "sim", "--duration", "5", "--gnss-protocol", "nmea", "--gnss-messages", "GGA"
    )
    assert line.startswith("hil: --gnss-protocol/--gnss-messages/--gnss-baud: nmea messages GGA "), line
    assert "no date (add RMC or ZDA)" in line, line


@pytest.mark.parametrize("cmd", ["sim", "up"])
@pytest.mark.parametrize(("flag", "value"), [("--gnss-messages", "GGA,RMC"), ("--gnss-baud", "9600")])
def test_a_wire_setting_without_a_wire_is_refused(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, cmd: str, flag: str, value: str
) -> None:
    """Without --gnss-protocol (or hil up's --gnss-serial/--gnss-tcp) it was silently ignored."""
    line = _refused(capsys, tmp_path, cmd, "--duration", "1", flag, value)
    assert line.startswith(f"hil: {flag} without --gnss-protocol: "), line
    assert "add --gnss-protocol nmea" in line, line


def test_an_unknown_protocol_is_said_without_stray_quotes(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    line = _refused(capsys, tmp_path, "sim", "--duration", "1", "--gnss-protocol", "rtcm")
    assert line == (
        "hil: --gnss-protocol/--gnss-messages/--gnss-baud: unknown GNSS wire protocol 'rtcm'; known: nmea, ubx"
    ), line


FUSION_REFUSED = [
    (
        ["--feedback", "ekf15"],
        "hil: --feedback: ['ekf15'] have no feedback form; give auto, none or names of ",
    ),
    (
        ["--ekf-calibration", "accel"],
        "hil: --ekf-calibration must be auto, none, gyro or gyro+accel; got 'accel'",
    ),
    (["--estimators", "bogus"], "hil: --estimators: unknown estimator(s) ['bogus']; known: "),
    (
        ["--estimators", "kfvel", "--feedback", "comp1"],
        "hil: --feedback comp1: comp1 not run (the fusion runs kfvel)",
    ),
    (
        ["--estimators", "ins", "--feedback", "kfvel"],
        "hil: --feedback kfvel: kfvel not run (the fusion runs the free INS alone)",
    ),
    (
        ["--estimators", "kfvel", "--ekf-calibration", "gyro"],
        "hil: --ekf-calibration gyro: ekf15, whose states they are, is not run",
    ),
]


@pytest.mark.parametrize("cmd", ["sim", "up"])
@pytest.mark.parametrize(("args", "said"), FUSION_REFUSED, ids=[" ".join(a) for a, _ in FUSION_REFUSED])
def test_a_fusion_choice_that_cannot_apply_is_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, cmd: str, args: list[str], said: str
) -> None:
    """hil sim said "hil: ValueError: feedback: ..."; a choice for an estimator not run was taken
    and had no effect."""
    assert _refused(capsys, tmp_path, cmd, "--duration", "1", *args).startswith(said)


def test_feedback_and_calibration_for_estimators_that_run_are_taken() -> None:
    from hil.nodes.fusion import FusionOptions

    assert (
        FusionOptions(estimators=["kfvel", "ekf15"], feedback="kfvel", ekf_calibration="gyro").unused_choice()
        == ""
    )
    assert (
        FusionOptions(feedback="comp1,cf3", ekf_calibration="gyro+accel").unused_choice() == ""
    )  # the defaults
    assert FusionOptions(estimators=["kfvel"], feedback="none", ekf_calibration="none").unused_choice() == ""


CAMPAIGN_REFUSED = [
    (
        ["sim", "--scenario", "static", "--runs", "0"],
        "hil campaign sim: error: argument --runs: '0' must be >= 1",
    ),
    (
        ["sim", "--scenario", "static", "--runs", "1", "--duration", "0"],
        "hil campaign sim: error: argument --duration: ",
    ),
    (
        ["sim", "--scenario", "static", "--runs", "1", "--duration", "inf"],
        "hil campaign sim: error: argument --duration: ",
    ),
    (
        ["sim", "--scenario", "static", "--runs", "1", "--workers", "0"],
        "hil campaign sim: error: argument --workers: ",
    ),
    (["builtin", "seed004", "--runs", "0"], "hil campaign builtin: error: argument --runs: '0' must be >= 1"),
]


@pytest.mark.parametrize(("args", "said"), CAMPAIGN_REFUSED, ids=[" ".join(a) for a, _ in CAMPAIGN_REFUSED])
def test_a_campaign_argument_error_is_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, args: list[str], said: str
) -> None:
    """hil campaign printed argparse's 8-line usage first."""
    out = tmp_path / "c"
    with pytest.raises(SystemExit) as ended:
        main(["campaign", *args, "--out", str(out)])
    assert ended.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(said), err
    assert not out.exists()


def test_hil_bench_name_help_shows_the_benchmark_s_own_options(capsys: pytest.CaptureFixture[str]) -> None:
    """-h was the bench subparser's: it showed the generic hil bench help and never ran the
    benchmark's parser."""
    with pytest.raises(SystemExit) as ended:
        main(["bench", "gnss", "--help"])
    assert ended.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: hil bench gnss "), out
    assert "--no-write" in out  # the gnss benchmark's own option


def test_hil_bench_help_lists_the_benchmarks(capsys: pytest.CaptureFixture[str]) -> None:
    from hil.cli import bench_names

    assert main(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: hil bench ") and f"benchmarks: {', '.join(bench_names())}" in out, out


def test_hil_bench_without_a_name_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hil: bench: name a benchmark: "), err


def test_hil_sim_help_says_what_fd_is(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["sim", "--help"])
    out = capsys.readouterr().out
    assert "CAN FD: one frame per IMU sample" in " ".join(out.split()), out


def _warned(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, *argv: str
) -> list[str]:
    """What ``hil sim argv`` warned before its run (stopped where the run would start)."""

    def start(*_args: object, **_kw: object) -> None:
        raise KeyboardInterrupt  # main: exit 130, nothing run

    monkeypatch.setattr("hil.runners.sim.run_sim", start)
    assert main(["sim", *argv, "--quiet", "--record", str(tmp_path / "run.mcap")]) == 130
    return [line for line in capsys.readouterr().err.splitlines() if "warning" in line]


def test_an_imu_rate_past_the_classic_can_bus_is_warned_with_its_load(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """2 kHz on classic CAN is 108.7 % of the bus (docs/can-protocol.md): the session stretched
    (5.435 s for --duration 5) and nothing said so."""
    (line,) = _warned(capsys, tmp_path, monkeypatch, "--imu-rate", "2000", "--duration", "5")
    assert line.startswith(
        "hil sim: warning: the IMU at 2000 Hz loads its classic CAN (4 frames a sample) bus to 108.7 %"
    )
    assert "use --fd (one frame a sample) or --imu-rate 1840 or lower" in line, line
    assert _warned(capsys, tmp_path, monkeypatch, "--imu-rate", "2000", "--fd", "--duration", "5") == []
    assert _warned(capsys, tmp_path, monkeypatch, "--imu-rate", "1000", "--duration", "5") == []


def test_the_warned_rate_is_the_bus_model_s_own() -> None:
    from hil.can.codec import ImuCanCodec

    codec = ImuCanCodec.from_dbc()
    assert codec.bus_load(1840) <= 1.0 < codec.bus_load(1841)
    assert (
        round(codec.bus_load(2000) * 100, 1) == 108.7
        and round(codec.bus_load(2000, fd=True) * 100, 1) == 21.6
    )


def test_a_gnss_baud_too_slow_for_the_message_set_is_warned_with_the_line_load(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """uav_survey's receiver sends 5 fixes a second: its default NMEA set overruns 9600 baud."""
    args = ["--scenario", "uav_survey", "--duration", "5", "--gnss-protocol", "nmea"]
    (line,) = _warned(capsys, tmp_path, monkeypatch, *args, "--gnss-baud", "9600")
    assert line.startswith(
        "hil sim: warning: the GNSS line at 9600 baud is loaded to 164.6 % by nmea at 5 fixes"
    ), line
    assert "use --gnss-baud 19200 or more, or fewer --gnss-messages" in line, line
    assert _warned(capsys, tmp_path, monkeypatch, *args, "--gnss-baud", "19200") == []


def test_the_line_load_is_what_the_uart_overruns_at() -> None:
    """Past a load of 1 the receiver's UART model drops epochs; at or below it, none."""
    from hil.nodes.gnss_emulator import TYPICAL_EPOCH, encoder, line_load
    from hil.wire.line import Uart

    n = len(encoder("nmea", [], "GN").encode_epoch(TYPICAL_EPOCH))
    for baud, over in ((9600, True), (19200, False)):
        assert (line_load(["nmea"], [], baud, 5.0) > 1.0) is over
        uart = Uart(baud)
        lost = sum(uart.send(n, k * 200_000_000) is None for k in range(100))
        assert (lost > 0) is over, (baud, lost)


def test_at_another_speed_the_bus_and_the_line_are_loaded_as_many_times_more() -> None:
    """``hil up --speed 2``: the rig sends twice as much a wall second on a bus and a line that
    keep their bit rates; the warnings were those of speed 1."""
    import argparse

    from hil.cli import _load_warnings
    from hil.nav.scenario import load_scenario

    uav = load_scenario("uav_survey")  # 5 fixes a second: 82.3 % of 19200 baud at speed 1
    wire = {"gnss_protocol": ["nmea"], "gnss_messages": [], "gnss_baud": 19200}
    at = argparse.Namespace(imu_rate=1000, fd=False, speed=1.0)
    assert _load_warnings(uav, at, wire) == []
    imu, line = _load_warnings(uav, argparse.Namespace(imu_rate=1000, fd=False, speed=2.0), wire)
    assert imu.startswith(
        "the IMU at 1000 Hz at --speed 2 loads its classic CAN (4 frames a sample) bus to 108.7"
    ), imu
    assert "--imu-rate 919 or lower" in imu, imu
    assert (
        _load_warnings(
            uav, argparse.Namespace(imu_rate=919, fd=False, speed=2.0), {**wire, "gnss_baud": 38400}
        )
        == []
    )
    assert line.startswith(
        "the GNSS line at 19200 baud is loaded to 164.6 % by nmea at 5 fixes a second at --speed 2"
    )
    assert "use --gnss-baud 38400 or more" in line, line
