"""The compiled strapdown (hil.runtime.jit) computes the Python one's bits, and a recording made with
either reruns bit for bit with the other."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.nav import kernels, strapdown
from hil.record.mcapio import read_session
from hil.runtime import jit

ROOT = Path(__file__).resolve().parents[2]


def _random_states(n: int, seed: int) -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    """States over the whole Earth and attitude sphere, increments of a 400 Hz consumer IMU; one
    in five with a rotation under the small-angle branch of the rotation-vector quaternion."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        st = (
            float(rng.uniform(-1.55, 1.55)),
            float(rng.uniform(-math.pi, math.pi)),
            float(rng.uniform(-400.0, 12000.0)),
            *rng.normal(0.0, 40.0, 3).tolist(),
            *q.tolist(),
            *rng.normal(0.0, 2e-3, 3).tolist(),
            *rng.normal(0.0, 3e-2, 3).tolist(),
        )
        th = rng.normal(0.0, 1e-9 if i % 5 == 0 else 2e-3, 3).tolist()
        dv = (rng.normal(0.0, 3e-2, 3) + np.array((0.0, 0.0, -9.81 * 0.0025))).tolist()
        out.append((st, (*th, *dv, 0.0025)))
    return out


def test_the_compiled_strapdown_step_computes_the_python_bits() -> None:
    assert jit.enable() == "compiled", "numba is a dependency: the kernels must compile here"
    assert kernels.compiled  # what the fusion's status reports
    python_step = jit.python_kernel("_step")
    assert strapdown._step is not python_step
    cases = _random_states(20000, seed=4)
    differing = [i for i, (st, a) in enumerate(cases) if strapdown._step(st, *a) != python_step(st, *a)]
    assert differing == []
    # and a long chain from one state, where any last-bit difference would grow
    st_c = st_p = cases[0][0]
    for _st, a in cases:
        st_c, st_p = strapdown._step(st_c, *a), python_step(st_p, *a)
    assert st_c == st_p


@pytest.mark.parametrize(
    ("gyro_cal", "accel_cal", "body_rate"), [(False, False, False), (True, True, True), (True, False, True)]
)
def test_the_compiled_strapdown_run_computes_the_python_bits(
    gyro_cal: bool, accel_cal: bool, body_rate: bool
) -> None:
    """The run of steps an estimator takes for a block of IMU intervals (biases, calibration
    matrices, the sums it carries), compiled against Python's on a long chain of intervals."""
    assert jit.enable() == "compiled"
    python_run = jit.python_kernel("_corrected_run")
    assert strapdown._corrected_run is not python_run
    rng = np.random.default_rng(7)
    cases = _random_states(3000, seed=5)
    rows = [(a[6], *a[:6]) for _st, a in cases]  # dt first, then Δθ, Δv: the block's rows
    array = np.array(rows, dtype=np.float64)
    bias = tuple((rng.normal(0.0, 1e-3, 6) * (1.0, 1.0, 1.0, 50.0, 50.0, 50.0)).tolist())
    e_g, e_a = tuple(rng.normal(0.0, 3e-3, 9).tolist()), tuple(rng.normal(0.0, 3e-3, 9).tolist())
    st0 = cases[0][0]
    got = want = (st0, (0.0, -0.0, 1e-3), (0.0, 0.0, 0.0), 0.0)
    for start in range(0, len(rows), 20):  # runs of 20, each from where the last one stopped
        stop = start + 20
        want = python_run(
            want[0], rows, start, stop, bias, e_g, e_a, *want[1:], gyro_cal, accel_cal, body_rate
        )
        got = strapdown._corrected_run(
            got[0], array, start, stop, bias, e_g, e_a, *got[1:], gyro_cal, accel_cal, body_rate
        )
        assert got == want, f"differs after interval {stop}"
    if gyro_cal or accel_cal:
        return
    # and without calibration the run is the per-interval step with the biases taken out
    step = jit.python_kernel("_step")
    bgx, bgy, bgz, bax, bay, baz = bias
    st = st0
    for dt, tx, ty, tz, ux, uy, uz in rows[:50]:
        st = step(
            st, tx - bgx * dt, ty - bgy * dt, tz - bgz * dt, ux - bax * dt, uy - bay * dt, uz - baz * dt, dt
        )
    zero = (0.0, 0.0, 0.0)
    assert python_run(st0, rows, 0, 50, bias, e_g, e_a, zero, zero, 0.0, False, False, body_rate)[0] == st


@pytest.mark.parametrize(
    ("value", "on", "warned"),
    [
        ("", True, False),
        ("0", False, False),
        ("off", False, False),
        ("1", True, False),
        ("numba", True, False),
        ("fast", True, True),
    ],
)
def test_hil_jit_values(value: str, on: bool, warned: bool, capsys: pytest.CaptureFixture[str]) -> None:
    wanted, why = jit._wanted({jit.JIT_ENV: value})
    assert wanted is on
    assert why.startswith("python") is (not on)
    err = capsys.readouterr().err
    assert ("HIL_JIT='fast' is not 0, 1 or numba" in err) is warned


def _hil(args: list[str], hil_jit: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, HIL_JIT=hil_jit, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-m", "hil.cli", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )


@pytest.mark.parametrize(("made", "rerun"), [("0", "1"), ("1", "0")])
def test_a_recording_reruns_bit_for_bit_with_the_kernels_the_other_way(
    tmp_path: Path, made: str, rerun: str
) -> None:
    """uav_survey's consumer IMU: the free INS, five feedback INS and ekf15 all step the strapdown;
    the fusion's status says which way it ran."""
    rec = tmp_path / "s.mcap"
    sim = _hil(
        ["sim", "--scenario", "uav_survey", "--duration", "8", "--record", str(rec), "--one-process"], made
    )
    assert sim.returncode == 0, sim.stderr
    statuses = [r.decode() for r in read_session(rec).records if r.topic.endswith("/status/fusion")]
    assert statuses and all(
        dict((c.key, c.value) for c in st.counters)["kernels.compiled"] == int(made) for st in statuses
    )
    res = _hil(["rerun", str(rec), "--core", "fusion", "--verify"], rerun)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "bit-identical" in res.stdout


@pytest.mark.parametrize("order", [1, 2, 3])
def test_the_compiled_filter_step_computes_einsums_bits(order: int) -> None:
    """The compensation filters' orders (1 to 3), six channels, operands over 16 decades and
    with signed zeros: the loop form adds einsum's terms in einsum's order."""
    from hil.estimators import compensation

    assert jit.enable() == "compiled"
    python_ramp = jit.python_kernel("_ramp_step")
    assert compensation._ramp_step is not python_ramp
    rng = np.random.default_rng(order)
    for _ in range(3000):
        m = rng.normal(size=(order, order + 2)) * 10.0 ** rng.integers(-8, 8, size=(order, order + 2))
        x = rng.normal(size=(order, 6)) * 10.0 ** rng.integers(-8, 8, size=(order, 6))
        u, s = rng.normal(size=6), rng.normal(size=6) * 1e-3
        x[rng.random(size=x.shape) < 0.1] = -0.0
        h = float(rng.uniform(1e-4, 2.0))
        xc, uc, xp, up = x.copy(), u.copy(), x.copy(), u.copy()
        compensation._ramp_step(m, xc, uc, s, h)  # both in place
        python_ramp(m, xp, up, s, h)
        assert xc.tobytes() == xp.tobytes() and uc.tobytes() == up.tobytes()
        assert xc.tobytes() != x.tobytes() or not m.any()  # it did step


def test_the_compiled_output_predictor_computes_the_python_bits() -> None:
    """The predictor's step onto its running sums and its carry of a horizon state (biases out or
    not; a window of a few ms to the 0.5 s horizon), compiled against Python on random states."""
    from hil.fusion import predictor

    assert jit.enable() == "compiled"
    py_advance, py_carry = jit.python_kernel("_advance"), jit.python_kernel("_carry")
    assert predictor._advance is not py_advance and predictor._carry is not py_carry
    rng = np.random.default_rng(11)
    for k in range(20000):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        sums = (float(rng.uniform(0.0, 0.5)), *q.tolist(), *rng.normal(0.0, 5.0, 6).tolist())
        incr = (
            *rng.normal(0.0, 1e-9 if k % 7 == 0 else 2e-3, 3).tolist(),
            *rng.normal(0.0, 3e-2, 3).tolist(),
        )
        got_a, want_a = predictor._advance(*sums, *incr, 0.0025), py_advance(*sums, *incr, 0.0025)
        assert np.array(got_a).tobytes() == np.array(want_a).tobytes()  # signed zeros too
        dq = rng.normal(size=4) * (0.05, 1.0, 1.0, 1.0) + (1.0, 0.0, 0.0, 0.0)
        state = (*rng.normal(0.0, 1e3, 3).tolist(), *rng.normal(0.0, 30.0, 3).tolist(), *q.tolist())
        motion = (
            float(rng.uniform(0.0, 0.5)),
            *(dq / np.linalg.norm(dq)).tolist(),
            *rng.normal(0.0, 5.0, 6).tolist(),
        )
        bias = (*rng.normal(0.0, 1e-2, 3).tolist(), *rng.normal(0.0, 0.3, 3).tolist())
        for biased in (False, True):
            got = predictor._carry(*state, *motion, 9.81, biased, *bias)
            want = py_carry(*state, *motion, 9.81, biased, *bias)
            assert np.array(got).tobytes() == np.array(want).tobytes(), (k, biased)


def test_the_compiled_output_rows_compute_the_python_bits() -> None:
    """One IMU sample's solutions in one call (``carry_rows``: every stream carried, biases out or
    not, its latitude, longitude and height, and whether it is finite), compiled against Python:
    the motionless case, a stream gone non-finite (not converted, flagged), and each row against
    ``predict_floats`` and ``ned_to_lla_one`` one by one, the path it replaced."""
    from hil.fusion import core, predictor
    from hil.nav.earth import _origin_floats, ned_to_lla_one

    assert jit.enable() == "compiled"
    py_rows = jit.python_kernel("carry_rows")
    assert predictor.carry_rows is not py_rows and core.carry_rows is predictor.carry_rows
    origin = (0.8806, 0.5327, 300.0)
    (o0, o1, o2), c = _origin_floats(*origin)
    pred = predictor.OutputPredictor(0, 9.81)
    rng = np.random.default_rng(15)
    for k in range(400):
        rows = []
        for i in range(7):
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            bias = (1.0, *rng.normal(0.0, 1e-2, 3), *rng.normal(0.0, 0.3, 3)) if i % 2 else (0.0,) * 7
            rows.append((*rng.normal(0.0, 1e3, 3), *rng.normal(0.0, 30.0, 3), *q, *bias))
        if k % 10 == 1:
            rows[3] = (*rows[3][:4], np.inf, *rows[3][5:])
        dq = rng.normal(size=4) * (0.05, 1.0, 1.0, 1.0) + (1.0, 0.0, 0.0, 0.0)
        motion = (
            0.0 if k % 10 == 0 else float(rng.uniform(0.0, 0.5)),
            (1.0, 0.0, 0.0, 0.0) if k % 10 == 0 else tuple((dq / np.linalg.norm(dq)).tolist()),
            tuple(rng.normal(0.0, 5.0, 3).tolist()),
            tuple(rng.normal(0.0, 5.0, 3).tolist()),
        )
        args = (motion[0], *motion[1], *motion[2], *motion[3], pred.g, o0, o1, o2, *c[0], *c[1], *c[2])
        got, want = predictor.carry_rows(np.array(rows), *args), py_rows(np.array(rows), *args)
        assert got.tobytes() == want.tobytes(), k
        for row, t in zip(rows, got.tolist(), strict=True):
            b = None if row[10] == 0.0 else tuple(row[11:17])
            pos, vel, q = pred.predict_floats(row[0:3], row[3:6], row[6:10], motion, b)
            assert t[0:10] == [*pos, *vel, *q]
            finite = all(math.isfinite(v) for v in t[0:10])
            assert t[13] == (1.0 if finite else 0.0)
            if finite:
                assert tuple(t[10:13]) == ned_to_lla_one(*pos, *origin)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_the_compiled_filter_output_computes_einsums_bits(order: int) -> None:
    """A compensation filter's output ``C x + D u`` (read at every published solution), compiled
    against einsum on random states, signed zeros and a ``D`` of zero or not."""
    from hil.estimators import compensation

    assert jit.enable() == "compiled"
    python_output = jit.python_kernel("_filter_output")
    assert compensation._filter_output is not python_output
    rng = np.random.default_rng(16 + order)
    for k in range(3000):
        x = rng.normal(size=(order, 6)) * 10.0 ** rng.uniform(-9, 3)
        x[rng.random((order, 6)) < 0.1] = -0.0
        c, u = rng.normal(size=order), rng.normal(size=6)
        d = 0.0 if k % 2 else float(rng.normal())
        assert compensation._filter_output(x, c, d, u).tobytes() == python_output(x, c, d, u).tobytes(), k


def test_the_compiled_corrector_prediction_computes_the_python_bits() -> None:
    """The feedback corrector's whole prediction (F, the covariance step, Φ δv), compiled with
    the compiled covariance step, against Python on random attitudes and covariances."""
    from hil.estimators import feedback

    assert jit.enable() == "compiled"
    python_run = jit.python_kernel("_corrector_prediction")
    assert feedback._corrector_prediction is not python_run
    rng = np.random.default_rng(24)
    for k in range(3000):
        q, p, qc = jit._prediction_operands(rng, 12)  # what jit's own check draws
        args = (
            *q,
            *rng.normal(0.0, 0.5, 3).tolist(),
            float(rng.uniform(0.01, 0.1)),
            float(rng.uniform(-1.5, 1.5)),
        )
        dv = rng.normal(0.0, 0.1, 3).tolist()
        if k % 5 == 0:
            dv[int(rng.integers(3))] = -0.0
        got_p, *got = feedback._corrector_prediction(*args, p, qc, *dv)
        want_p, *want = python_run(*args, p, qc, *dv)
        assert got_p.tobytes() == want_p.tobytes() and np.array(got).tobytes() == np.array(want).tobytes(), k


@pytest.mark.parametrize(("cal", "acal"), [(False, False), (True, False), (True, True)])
def test_the_compiled_ekf15_dynamics_compute_the_python_bits(cal: bool, acal: bool) -> None:
    """ekf15's F written in place (its frame terms, the calibration blocks' einsum products),
    compiled, against Python on random attitudes and increments of each state layout: the F
    left in the template and the specific force, byte for byte."""
    from hil.estimators import ekf15

    assert jit.enable() == "compiled"
    python_run = jit.python_kernel("write_dynamics")
    assert ekf15.write_dynamics is not python_run
    rng = np.random.default_rng(27)
    for k in range(2000):
        q, _p, _qc = jit._prediction_operands(rng, 1)
        incr = rng.normal(0.0, 0.1, 6)
        if k % 7 == 0:
            incr[rng.integers(6)] = -0.0
        args = (
            *q,
            *incr.tolist(),
            0.01,
            float(rng.uniform(-1.5, 1.5)),
            cal,
            acal,
            24 if cal else 15,
        )
        f_c, f_p = ekf15.dynamics_template(cal, acal, 0.0), ekf15.dynamics_template(cal, acal, 0.0)
        got, want = ekf15.write_dynamics(f_c, *args), python_run(f_p, *args)
        assert f_c.tobytes() == f_p.tobytes() and np.array(got).tobytes() == np.array(want).tobytes(), k


def _covariance_operands(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``F`` from dense to empty with signed zeros, a covariance ``P`` (some with zero entries)
    and a diagonal ``Q_c``."""
    f = (
        rng.normal(size=(n, n))
        * 10.0 ** rng.integers(-6, 3, size=(n, n))
        * (rng.random((n, n)) < rng.random())
    )
    f[rng.random((n, n)) < 0.1] = -0.0
    a = rng.normal(size=(n, n))
    p = a @ a.T
    if rng.random() < 0.2:
        p[rng.random((n, n)) < 0.2] = 0.0
    return f, p, np.diag(rng.random(n))


def test_the_compiled_covariance_step_computes_einsums_bits() -> None:
    """ekf15's and the corrector's ``Φ P Φ' + Q`` (every size to 40, ``F`` of any sparsity): the
    products skip zero terms and still add einsum's terms in einsum's orders, byte for byte."""
    from hil.estimators import ekf15, feedback

    assert jit.enable() == "compiled"
    python_cov = jit.python_kernel("covariance_step")
    assert ekf15.covariance_step is not python_cov
    assert feedback.covariance_step is ekf15.covariance_step  # the corrector's too
    rng = np.random.default_rng(12)
    differing = []
    for trial in range(2000):
        n = int(rng.integers(2, 41))
        f, p, qc = _covariance_operands(rng, n)
        dt = float(rng.uniform(1e-3, 0.1))
        got, want = ekf15.covariance_step(f, dt, p, qc), python_cov(f, dt, p, qc)
        if got[0].tobytes() != want[0].tobytes() or got[1].tobytes() != want[1].tobytes():
            differing.append((trial, n))
    assert differing == []


def test_the_compiled_covariance_step_on_non_finite_and_non_contiguous_operands() -> None:
    """A diverged ``P`` (∞, NaN): no zero term is skipped against a non-finite factor, so the
    NaNs and infinities land where einsum's do. A Fortran-ordered operand (einsum may add it in
    another order) goes to the Python kernel."""
    from hil.estimators import ekf15

    assert jit.enable() == "compiled"
    python_cov = jit.python_kernel("covariance_step")
    rng = np.random.default_rng(13)
    for _ in range(300):
        n = int(rng.integers(2, 25))
        f, p, qc = _covariance_operands(rng, n)
        p[rng.integers(n), rng.integers(n)] = rng.choice([np.inf, -np.inf, np.nan])
        with np.errstate(invalid="ignore", over="ignore"):
            got, want = ekf15.covariance_step(f, 0.01, p, qc), python_cov(f, 0.01, p, qc)
        assert np.array_equal(got[1], want[1], equal_nan=True)
        assert got[0].tobytes() == want[0].tobytes()
    f, p, qc = _covariance_operands(rng, 15)
    got, want = (
        ekf15.covariance_step(np.asfortranarray(f), 0.01, p, qc),
        python_cov(np.asfortranarray(f), 0.01, p, qc),
    )
    assert got[1].tobytes() == want[1].tobytes()


def test_the_compiled_fix_update_computes_the_python_bits() -> None:
    """ekf15's Joseph-form update of a position or velocity fix (every state layout, with and
    without an antenna arm, sparse and signed-zero covariances): ``δx``, ``P+`` and the NIS byte
    for byte. A singular ``S`` raises as the Python one does, and a measurement of other than 3
    rows or a Fortran-ordered operand goes to the Python kernel."""
    from hil.estimators import ekf15

    assert jit.enable() == "compiled"
    python_update = jit.python_kernel("kf_update")
    assert ekf15.kf_update is not python_update
    rng = np.random.default_rng(14)
    differing = []
    for trial in range(600):
        n = int(rng.choice([15, 21, 24, 27, 30, 33, 39]))
        p, y, h, r = jit.update_operands(rng, n, lever=bool(trial % 2))
        if trial % 5 == 0:
            p[rng.random((n, n)) < 0.2] = 0.0
            p[rng.random((n, n)) < 0.05] = -0.0
        got, want = ekf15.kf_update(p, y, h, r), python_update(p, y, h, r)
        if (
            got[0].tobytes() != want[0].tobytes()
            or got[1].tobytes() != want[1].tobytes()
            or got[2] != want[2]
        ):
            differing.append((trial, n))
    assert differing == []
    p, y, h, r = jit.update_operands(rng, 15, lever=True)
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        ekf15.kf_update(p, y, np.zeros_like(h), np.zeros((3, 3)))
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        python_update(p, y, np.zeros_like(h), np.zeros((3, 3)))
    two = h[:2].copy()
    got, want = (
        ekf15.kf_update(p, y[:2], two, r[:2, :2].copy()),
        python_update(p, y[:2], two, r[:2, :2].copy()),
    )
    assert got[1].tobytes() == want[1].tobytes() and got[2] == want[2]
    got, want = ekf15.kf_update(np.asfortranarray(p), y, h, r), python_update(np.asfortranarray(p), y, h, r)
    assert got[1].tobytes() == want[1].tobytes()


def test_the_compiled_corrector_update_computes_the_python_bits() -> None:
    """The feedback corrector's velocity fix (12 states, ``H = [I 0 0 0]``): ``S⁻¹`` and the NIS,
    then ``P+`` and ``δx``, byte for byte on dense, sparse and signed-zero covariances; a
    singular ``S`` raises as the Python one does, a Fortran-ordered ``P`` goes to the Python one."""
    from hil.estimators import feedback

    assert jit.enable() == "compiled"
    innovation, joseph = jit.python_kernel("corrector_innovation"), jit.python_kernel("corrector_joseph")
    assert feedback.corrector_innovation is not innovation and feedback.corrector_joseph is not joseph
    rng = np.random.default_rng(15)
    differing = []
    for trial in range(400):
        p, y, _h, r = jit.update_operands(rng, 12, lever=False)
        if trial % 5 == 0:
            p[rng.random((12, 12)) < 0.2] = 0.0
            p[rng.random((12, 12)) < 0.05] = -0.0
        got, want = feedback.corrector_innovation(p, y, r), innovation(p, y, r)
        if got[0].tobytes() != want[0].tobytes() or got[1] != want[1]:
            differing.append(("innovation", trial))
        got2, want2 = feedback.corrector_joseph(p, want[0], y, r), joseph(p, want[0], y, r)
        if got2[0].tobytes() != want2[0].tobytes() or got2[1].tobytes() != want2[1].tobytes():
            differing.append(("joseph", trial))
    assert differing == []
    p, y, _h, r = jit.update_operands(rng, 12, lever=False)
    p[0:3, 0:3] = 0.0
    for fn in (feedback.corrector_innovation, innovation):
        with pytest.raises(np.linalg.LinAlgError, match="singular"):
            fn(p, y, np.zeros((3, 3)))
    p, y, _h, r = jit.update_operands(rng, 12, lever=False)
    s_inv = innovation(p, y, r)[0]
    fortran = np.asfortranarray(p)  # einsum adds in another order there: the Python one's bits
    got2, want2 = feedback.corrector_joseph(fortran, s_inv, y, r), joseph(fortran, s_inv, y, r)
    assert got2[0].tobytes() == want2[0].tobytes()


def test_the_compiled_expm_computes_the_portable_bits() -> None:
    """``e^M`` of the ZOH filters (orders to 3, plus the ramp's two states) and beyond, any
    sparsity and norm (scaling and squaring from a nanosecond step to norms of ~30): byte-equal
    to :func:`hil.nav.portable.expm`; and the filters' own matrices through ``ramp_hold``."""
    from hil.estimators import lti

    assert jit.enable() == "compiled"
    python_expm = jit.python_kernel("expm")
    assert lti.expm is not python_expm
    rng = np.random.default_rng(14)
    differing = []
    for trial in range(6000):
        n = int(rng.integers(1, 9))
        m = rng.normal(size=(n, n)) * (rng.random((n, n)) < rng.random()) * 10.0 ** rng.uniform(-10, 1.5)
        m[rng.random((n, n)) < 0.05] = -0.0
        if lti.expm(m).tobytes() != python_expm(m).tobytes():
            differing.append((trial, n))
    assert differing == []
    # a matrix Python cannot take raises Python's exception, never a garbage exponent
    for bad, kind in ((np.nan, ValueError), (np.inf, OverflowError), (1e308, OverflowError)):
        m = np.eye(3)
        m[1, 2] = bad
        for fn in (lti.expm, python_expm):
            with pytest.raises(kind):
                fn(m)
    ss = lti.StateSpace.from_tf(lti.forcing3(5.0))
    compiled_expm = lti.expm
    for h_ns in (1, 2_499_950, 2_500_000, 1_000_000_000, 7_300_000_001):
        got = lti.ramp_hold(ss, h_ns * 1e-9)
        lti.expm = python_expm
        try:
            want = lti.ramp_hold(ss, h_ns * 1e-9)
        finally:
            lti.expm = compiled_expm
        assert all(g.tobytes() == w.tobytes() for g, w in zip(got, want, strict=True))


def test_the_compiled_ecef_to_lla_computes_the_python_bits() -> None:
    """Every published solution's latitude, longitude and height: over the whole Earth from 500 m
    below the ellipsoid to 20 km above (and off it), the compiled conversion (the C library's
    ``hypot``, CPython's ``pow``) gives the Python one's bits, through ``ned_to_lla_one`` too."""
    from hil.nav import earth

    assert jit.enable() == "compiled"
    python_lla = jit.python_kernel("ecef_to_lla_one")
    assert earth._ecef_to_lla_one is not python_lla
    rng = np.random.default_rng(15)
    points = [
        earth._ecef_one(
            rng.uniform(-1.5707, 1.5707), rng.uniform(-math.pi, math.pi), rng.uniform(-500.0, 2e4)
        )
        for _ in range(40000)
    ]
    points += [tuple(rng.normal(0.0, 7e6, 3).tolist()) for _ in range(10000)]
    assert [p for p in points if earth._ecef_to_lla_one(*p) != python_lla(*p)] == []
    ned = rng.normal(0.0, 5e4, (2000, 3)).tolist()
    got = [earth.ned_to_lla_one(*d, 0.8, 0.1, 120.0) for d in ned]
    earth._ecef_to_lla_one = python_lla
    try:
        want = [earth.ned_to_lla_one(*d, 0.8, 0.1, 120.0) for d in ned]
    finally:
        earth._ecef_to_lla_one = jit.compiled_kernel("ecef_to_lla_one")
    assert got == want


def test_kernels_loaded_in_the_background_take_over_a_running_core() -> None:
    """The live service's way: the kernels load in a thread while the core already steps with the
    Python ones; the states the core reaches are the same bits either way."""
    code = (
        "from hil.nav import kernels, strapdown\n"
        "from hil.runtime import jit\n"
        "s = strapdown.StrapdownState(0.8, 0.1, 100.0, (10.0, 2.0, -1.0), (1.0, 0.0, 0.0, 0.0))\n"
        "a = (1e-3, -2e-4, 3e-4, 0.01, -0.02, -0.0245, 0.0025)\n"
        "t = jit.enable_in_background()\n"
        "n = 0\n"
        "while t.is_alive() or n < 1000:\n"
        "    s = strapdown.strapdown_step_f(s, *a); n += 1\n"
        "r = strapdown.StrapdownState(0.8, 0.1, 100.0, (10.0, 2.0, -1.0), (1.0, 0.0, 0.0, 0.0))\n"
        "py = jit.python_kernel('_step')\n"
        "for _ in range(n): r = strapdown._new(strapdown.StrapdownState, py(tuple(r), *a))\n"
        "print(jit.state(), kernels.compiled, n > 1000, tuple(s) == tuple(r))\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop(jit.JIT_ENV, None)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["compiled", "True", "True", "True"]


def test_the_compiled_square_is_cpythons_pow_not_a_multiply() -> None:
    """CPython's ``x**2`` is the C library's ``pow(x, 2)``, which differs from ``x * x`` in about
    one value in a thousand; a compiled ``x**2`` would be ``x * x``. Found by a 1200 s rerun in
    Python of a recording made compiled: ekf15's velocity differed in the 13th digit after 1018 s."""
    assert jit.enable() == "compiled"
    rng = np.random.default_rng(7)
    xs = np.concatenate([rng.uniform(-1.6, 1.6, 300_000), rng.normal(0.0, 1e3, 100_000)]).tolist()
    assert sum(1 for x in xs if x**2 != x * x) > 100  # the case exists in this sample
    compiled = jit.compiled_kernel("libm_square")
    assert [x for x in xs if compiled(x) != x**2] == []


def test_sin_and_cos_of_one_angle_keep_their_bits_when_the_compiler_pairs_them() -> None:
    """LLVM turns ``math.sin(x), math.cos(x)`` into one ``sincos`` call (the strapdown takes both
    of the latitude); the C library's sincos gives sin's and cos's bits."""
    import numba

    @numba.njit(cache=False)
    def sin_cos_tan(x: float) -> tuple[float, float, float]:
        return math.sin(x), math.cos(x), math.tan(x)

    rng = np.random.default_rng(11)
    xs = np.concatenate([rng.uniform(-1.6, 1.6, 200_000), rng.normal(0.0, 1e-3, 50_000)]).tolist()
    assert [x for x in xs if sin_cos_tan(x) != (math.sin(x), math.cos(x), math.tan(x))] == []


def test_bench_jit_reruns_a_compiled_recording_in_python_and_compiled(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from hil.bench import jit as bench_jit

    rc = bench_jit.main(["--duration", "3", "--repeat", "1", "--no-write"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "| Python (`HIL_JIT=0`) |" in out and "| numba's cache (`HIL_JIT=numba`) |" in out
    jit.enable()
    built = jit.source().startswith("ahead of time")  # make built them for these sources
    assert ("| ahead of time (`HIL_JIT=1`, `make`) |" in out) is built
    assert "FAILED" not in out and "numba / Python **" in out
