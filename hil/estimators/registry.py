"""One factory for every live estimator: ``make_estimator(name, init, params)``.

Names are short and stable: they become Zenoh keys ``hil/<rig>/nav/<name>``.

| name | what | params (defaults) |
| --- | --- | --- |
| comp1 | compensation, classic ``1/(Tp+1)`` | ``t_s`` (5.0), ``restart_after_s`` (3.0) |
| comp2 | compensation, ``1/(Tp+1)²`` | same |
| comp3 | compensation, ``1/(Tp+1)³`` | same |
| comp3f | compensation, forcing ``(3Tp+1)/(Tp+1)³`` | same |
| compvs | compensation, variable structure (seed 000 table) | ``restart_after_s`` (3.0) |
| cf2 | complementary ``W = (r1 s + r2)/(s² + r1 s + r2)`` as compensation | ``r1`` (0.07), ``r2`` (0.005) |
| cf3 | complementary third order, coasts | ``k1`` (0.07), ``k2`` (0.005), ``k3`` (1e-4), see below |
| kfvel | lecture scalar KFs per axis, position and velocity | ``q_pos_m2ps``, ``q_vel_m2ps3``, ... |
| ekf15 | 3-D loosely coupled error-state EKF | see :mod:`hil.estimators.ekf15` |

Every compensation filter takes ``gnss_coast`` (True; False: the last difference continued
through a GNSS gap, as a recording made before the coasts ran). cf3 also takes ``coast_after``
(2.5 input intervals; None: no coast) and ``innovation_tau_s`` (3.0): its own coast through a
gap (:class:`hil.estimators.compensation.CompensationCore`) instead of the others' line.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from hil.estimators.base import Estimator, InitialState
from hil.estimators.compensation import VS_SCHEDULE, CompensationEstimator, fixed_filter
from hil.estimators.lti import complementary2, complementary3
from hil.estimators.scalar_kf import ScalarKfEstimator

Factory = Callable[[str, InitialState, dict[str, Any]], Estimator]


def _fixed(kind: str) -> Factory:
    def make(name: str, init: InitialState, p: dict[str, Any]) -> Estimator:
        tf = fixed_filter(kind, float(p.get("t_s", 5.0)))
        return CompensationEstimator(
            name,
            init,
            ((0.0, tf),),
            p.get("restart_after_s", 3.0),
            p.get("feedback"),
            line_coast=bool(p.get("gnss_coast", True)),
        )

    return make


def _compvs(name: str, init: InitialState, p: dict[str, Any]) -> Estimator:
    return CompensationEstimator(
        name,
        init,
        VS_SCHEDULE,
        p.get("restart_after_s", 3.0),
        p.get("feedback"),
        line_coast=bool(p.get("gnss_coast", True)),
    )


def _cf2(name: str, init: InitialState, p: dict[str, Any]) -> Estimator:
    tf = complementary2(float(p.get("r1", 0.07)), float(p.get("r2", 0.005)))
    return CompensationEstimator(
        name, init, ((0.0, tf),), None, p.get("feedback"), line_coast=bool(p.get("gnss_coast", True))
    )


def _cf3(name: str, init: InitialState, p: dict[str, Any]) -> Estimator:
    tf = complementary3(float(p.get("k1", 0.07)), float(p.get("k2", 0.005)), float(p.get("k3", 1e-4)))
    # its own coast (open loop), not the line coast: on cf3 the line took the gate scenario's
    # window to 0.51 m (own coast 0.245 m, none 0.344 m) and car_drive's tunnel, in the feedback
    # form, from 2.32 m to 6.11 m
    coast = p.get("coast_after", 2.5) if p.get("gnss_coast", True) else None
    return CompensationEstimator(
        name,
        init,
        ((0.0, tf),),
        None,
        p.get("feedback"),
        None if coast is None else float(coast),
        float(p.get("innovation_tau_s", 3.0)),
        line_coast=False,
    )


def _kfvel(name: str, init: InitialState, p: dict[str, Any]) -> Estimator:
    return ScalarKfEstimator(name, init, **p)


def _ekf15(name: str, init: InitialState, p: dict[str, Any]) -> Estimator:
    from hil.estimators.ekf15 import Ekf15  # lazy: needs the strapdown

    return Ekf15(name, init, **p)


ESTIMATORS: dict[str, Factory] = {
    "comp1": _fixed("comp1"),
    "comp2": _fixed("comp2"),
    "comp3": _fixed("comp3"),
    "comp3f": _fixed("comp3f"),
    "compvs": _compvs,
    "cf2": _cf2,
    "cf3": _cf3,
    "kfvel": _kfvel,
    "ekf15": _ekf15,
}

DEFAULT_ESTIMATORS: tuple[str, ...] = ("comp1", "comp3f", "compvs", "cf3", "kfvel", "ekf15")

#: The seed family: each also runs in a feedback form (``params["feedback"]``,
#: :mod:`hil.estimators.feedback`), the INS reset by its estimate.
FEEDBACK_CAPABLE: tuple[str, ...] = ("comp1", "comp2", "comp3", "comp3f", "compvs", "cf2", "cf3", "kfvel")
#: ekf15's optional sensor-calibration states: none, the gyro's scale factor and misalignment
#: (9 states), and the accelerometer's too (9 more).
EKF_CALIBRATIONS: tuple[str, ...] = ("", "gyro", "gyro+accel")


def default_feedback(grade: str, estimators: tuple[str, ...]) -> tuple[str, ...]:
    """The estimators that run in feedback form on an IMU of ``grade`` (``imu_grade``).

    A consumer MEMS INS leaves every open-loop seed filter within minutes (its tilt drives the
    INS error's acceleration to g, which ``1 − F`` leaks as ``3T²·ξ̈``); a tactical or better
    INS stays inside it for the runs the rig makes, where the open-loop form is the papers' own
    (docs/estimators.md, "Open loop or feedback").
    """
    return tuple(e for e in estimators if e in FEEDBACK_CAPABLE) if grade == "consumer" else ()


def default_ekf_calibration(grade: str) -> str:
    """ekf15's calibration states on an IMU of ``grade``: the gyros' and the accelerometers'
    scale factor and misalignment for consumer MEMS (5000 ppm, 5 mrad: degrees of heading and
    tilt per turn; the accelerometers' take tilt from 0.17° to 0.13° RMS on uav_survey, so
    they are carried too), none for the better grades (docs/estimators.md)."""
    return "gyro+accel" if grade == "consumer" else ""


_NAME = re.compile(r"^[a-z0-9_]+$")


def make_estimator(name: str, init: InitialState, params: dict[str, Any] | None = None) -> Estimator:
    """Build the estimator registered as ``name``; ``params`` are never mutated."""
    if not _NAME.match(name):
        raise ValueError(f"estimator name {name!r} must match [a-z0-9_]+ (it is a Zenoh key)")
    try:
        factory = ESTIMATORS[name]
    except KeyError as err:
        raise KeyError(f"unknown estimator {name!r}; known: {sorted(ESTIMATORS)}") from err
    return factory(name, init, dict(params or {}))
