"""Replay is bit-identical whatever BLAS kernel or SIMD level the machine has.

The golden recording was once made on a machine whose OpenBLAS chose its SkylakeX kernel; on an
AMD EPYC (Haswell kernel) two estimators (cf3, comp3f) then differed in the last bit and ``hil
rerun --verify`` failed. Here the fusion's digest of the golden recording and a ``hil sim`` file are
computed again in child processes that run numpy on another BLAS kernel (OpenBLAS's generic
``Prescott``, which every x86-64 CPU runs: the opposite of the unsafe auto-detection the
machine's own OPENBLAS_CORETYPE guards against) and with every run-time SIMD dispatch of numpy
switched off (an AVX2-only or older CPU), and must come out identical.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm as scipy_expm

from hil.nav import portable
from tests.conftest import hil_cmd

ROOT = Path(__file__).resolve().parents[2]
x86_only = pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="x86-64 kernels")


def _dispatched_features() -> str:
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    return ",".join(f for f in __cpu_dispatch__ if __cpu_features__.get(f))


def _variants() -> dict[str, dict[str, str]]:
    out = {"blas-prescott": {"OPENBLAS_CORETYPE": "Prescott"}}
    feats = _dispatched_features()
    if feats:
        out["no-simd-dispatch"] = {"NPY_DISABLE_CPU_FEATURES": feats}
    return out


_DIGEST = """
import json
import math
from tests.replay.golden_update import GOLDEN, digest
from hil.record.rerun import rerun
d = digest(GOLDEN)
rc, lines = rerun(str(GOLDEN), core="timesync", verify=True)
print(json.dumps({"fusion": d, "timesync_rc": rc}))
"""


def _digest_in(env_extra: dict[str, str]) -> dict[str, object]:
    env = dict(os.environ, PYTHONPATH=str(ROOT), **env_extra)
    proc = subprocess.run(
        [sys.executable, "-c", _DIGEST], env=env, cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


@x86_only
def test_golden_rerun_is_bit_identical_on_another_blas_kernel_and_without_simd_dispatch() -> None:
    base = _digest_in({})
    assert base["timesync_rc"] == 0
    for name, env in _variants().items():
        got = _digest_in(env)
        assert got == base, f"{name} ({env}): the rerun differs from this machine's default"


@x86_only
def test_hil_sim_writes_the_same_file_on_another_blas_kernel_and_without_simd_dispatch(
    tmp_path: Path,
) -> None:
    def sim(tag: str, env_extra: dict[str, str]) -> bytes:
        out = tmp_path / f"{tag}.mcap"
        env = dict(os.environ, **env_extra)
        args = ["sim", "--scenario", "uav_survey", "--duration", "8", "--record", str(out), "--rig", "p"]
        proc = subprocess.run(hil_cmd(*args), env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        return out.read_bytes()

    base = sim("base", {})
    for name, env in _variants().items():
        assert sim(name, env) == base, f"{name} ({env}): hil sim wrote a different file"


def test_portable_algebra_agrees_with_blas_and_scipy_to_rounding() -> None:
    rng = np.random.default_rng(11)
    for n in (1, 3, 6, 15, 21):
        a, b = rng.standard_normal((n, n)), rng.standard_normal((n, n))
        x = rng.standard_normal(n)
        np.testing.assert_allclose(portable.mm(a, b), a @ b, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(portable.mmt(a, b), a @ b.T, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(portable.mv(a, x), a @ x, rtol=1e-12, atol=1e-12)
        assert portable.dot(x, x) == pytest.approx(float(x @ x), rel=1e-13)
        spd = a @ a.T + n * np.eye(n)
        np.testing.assert_allclose(portable.solve(spd, x), np.linalg.solve(spd, x), rtol=1e-10)
        np.testing.assert_allclose(portable.inv(spd) @ spd, np.eye(n), atol=1e-10)
    # a pivot is needed: zero on the diagonal
    perm = np.array([[0.0, 2.0], [3.0, 1.0]])
    np.testing.assert_allclose(portable.solve(perm, np.array([4.0, 5.0])), [1.0, 2.0])
    with pytest.raises(np.linalg.LinAlgError):
        portable.solve(np.array([[1.0, 2.0], [2.0, 4.0]]), np.array([1.0, 1.0]))


def test_portable_expm_matches_scipy_across_norms() -> None:
    rng = np.random.default_rng(12)
    for scale in (1e-4, 0.05, 0.5, 3.0, 40.0):
        m = rng.standard_normal((5, 5)) * scale - 0.3 * scale * np.eye(5)  # stable, like the filters
        ref = scipy_expm(m)
        np.testing.assert_allclose(portable.expm(m), ref, rtol=1e-12, atol=1e-13 * np.abs(ref).max())
    # the compensation filters' augmented matrix over a 1 s GNSS step (T = 0.5 s: norm ~ 7)
    a = np.array([[-6.0, -12.0, -8.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    aug = np.zeros((5, 5))
    aug[:3, :3], aug[0, 3], aug[3, 4] = a, 1.0, 1.0
    # entries that are ~0 agree to a few ulp of the largest (scaling and squaring vs Padé)
    np.testing.assert_allclose(portable.expm(aug), scipy_expm(aug), rtol=1e-12, atol=1e-14)


def test_portable_atan2_is_math_atan2_elementwise() -> None:
    y = np.array([0.3, -1.0, 0.0, 2.0])
    x = np.array([1.0, -0.5, -1.0, 0.0])
    got = portable.atan2(y, x)
    assert got.dtype == np.float64 and got.shape == (4,)
    assert list(got) == [math.atan2(a, b) for a, b in zip(y, x, strict=True)]
