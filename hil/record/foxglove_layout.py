"""The Foxglove layout shipped in ``docs/foxglove-layout.json``, built with the SDK's own layout
types (``foxglove.layouts``) so it is a layout Foxglove reads, not a hand-written guess.

python -m hil.record.foxglove_layout                    # print it (rig "bench")
python -m hil.record.foxglove_layout --rig sim --write  # ... or write docs/foxglove-layout.json

What it shows (every topic is one a recording or ``hil foxglove`` has; ``docs/recording.md``):

- Map: truth, the GNSS fixes and every estimator (``/foxglove/fix/...``), following truth;
- 3D: the frame tree (``enu``, ``ned``, ``truth``, ``nav/<est>``, ``sensor/gnss``), following truth;
- Plots: each estimator's north and east position error against truth is what ``hil report``
  computes; Foxglove's plot cannot subtract two topics, so the layout plots what the messages
  hold: position north/east of truth and every estimator on one axis (the gap is the error),
  ekf15's own 1-sigma and its normalised innovations (NIS, ``health/ekf15``), the fusion's
  consumed inputs and rejections (its ``status``, ``counters[:]{key=="..."}``);
- Log: events and service errors (``/foxglove/log``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import foxglove.layouts as fl

from hil.estimators.registry import DEFAULT_ESTIMATORS

DOC_PATH = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"
ESTIMATORS = ("ins", *DEFAULT_ESTIMATORS)


def _map(estimators: tuple[str, ...]) -> fl.MapPanel:
    topics = [
        "/foxglove/fix/truth",
        "/foxglove/fix/sensor/gnss",
        *(f"/foxglove/fix/nav/{e}" for e in estimators),
    ]
    return fl.MapPanel(
        title="Map: truth, GNSS, estimators",
        config=fl.MapConfig(
            follow_topic="/foxglove/fix/truth",
            zoom_level=17,
            topic_config={
                t: fl.MapTopicSettings(history_mode="all", show_heading=t != "/foxglove/fix/sensor/gnss")
                for t in topics
            },
        ),
    )


def _three_d() -> fl.ThreeDeePanel:
    return fl.ThreeDeePanel(
        title="3D: frame tree (enu root)",
        config=fl.ThreeDeeConfig(follow_tf="truth", follow_mode="follow-position"),
    )


def _series(path: str, label: str) -> fl.PlotSeries:
    return fl.PlotSeries(value=path, label=label, timestamp_method="receiveTime")


def _plots(rig: str, estimators: tuple[str, ...]) -> fl.SplitContainer:
    root = f"hil/{rig}"
    position = [
        fl.PlotPanel(
            title=f"Position {axis} [m]: truth and estimators (the gap is the error)",
            config=fl.PlotConfig(
                paths=[
                    _series(f"{root}/truth.pos_ned_m[{i}]", "truth"),
                    *(_series(f"{root}/nav/{e}.pos_ned_m[{i}]", e) for e in estimators),
                ],
                show_legend=True,
            ),
        )
        for i, axis in ((0, "north"), (1, "east"))
    ]
    ekf = fl.PlotPanel(
        title="ekf15: 1-sigma [m] and NIS",
        config=fl.PlotConfig(
            paths=[
                *(_series(f"{root}/nav/ekf15.pos_sigma_m[{i}]", f"sigma {a}") for i, a in enumerate("NED")),
                _series(f"{root}/health/ekf15.values[0]", "nis_pos"),
                _series(f"{root}/health/ekf15.values[1]", "nis_vel"),
            ],
            show_legend=True,
        ),
    )
    fusion = fl.PlotPanel(
        title="fusion: inputs consumed, rejected late",
        config=fl.PlotConfig(
            paths=[
                _series(f'{root}/status/fusion.counters[:]{{key=="consumed"}}.value', "consumed"),
                _series(
                    f'{root}/status/fusion.counters[:]{{key=="dropped_late.gnss"}}.value',
                    "dropped late (GNSS)",
                ),
            ],
            show_legend=True,
        ),
    )
    return fl.SplitContainer(
        direction="column",
        items=[fl.SplitItem(content=p) for p in (*position, ekf, fusion)],
    )


def layout(rig: str = "bench", estimators: tuple[str, ...] = ESTIMATORS) -> fl.Layout:
    left = fl.SplitContainer(
        direction="column",
        items=[
            fl.SplitItem(proportion=2, content=_map(estimators)),
            fl.SplitItem(proportion=2, content=_three_d()),
            fl.SplitItem(
                proportion=1,
                content=fl.LogPanel(title="Log: events, service errors", config=fl.LogConfig(show_name=True)),
            ),
        ],
    )
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=1, content=left),
                fl.SplitItem(proportion=1, content=_plots(rig, estimators)),
            ],
        )
    )


def layout_json(rig: str = "bench") -> str:
    import json

    return json.dumps(json.loads(layout(rig).to_json()), indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="the Foxglove layout for a rig's recordings and live view")
    ap.add_argument("--rig", default="bench", help="the rig whose hil/<rig>/... topics the plots show")
    ap.add_argument("--write", action="store_true", help=f"write {DOC_PATH}")
    a = ap.parse_args(argv)
    text = layout_json(a.rig)
    if a.write:
        DOC_PATH.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
