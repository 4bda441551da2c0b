"""Linear time-invariant building blocks shared by the compensation and complementary filters.

A filter ``F(p) = num(p) / den(p)`` (polynomials in the Laplace variable ``p``, highest power
first) is realised in controllable canonical state space ``ẋ = A x + B u, y = C x + D u`` and
discretised **exactly** for whatever step it is advanced by, with a zero-order hold (ZOH):

    Φ(h) = e^{A h}            Γ(h) = ∫_0^h e^{A s} ds · B

Why a hold-exact discretisation: the filter's input is the difference ``X_INS − X_GNSS``
formed at each GNSS epoch (1–10 Hz) and continued until the next one, while the filter is
advanced at IMU rate (400 Hz) and at the GNSS times of validity. Between fixes the input is a
known function of time — a ramp ``d_k + s_k (t − t_k)`` whose slope is the INS-minus-GNSS
velocity difference for the position channels (0 for velocity channels) — and for such an
input the matrix exponential of the augmented system is not an approximation but the exact
solution of the continuous filter, for any step length and any mix of step lengths. A plain
ZOH (``scipy.signal.cont2discrete(method="zoh")``, which gives the same ``Φ`` and ``Γ0``)
would delay a drifting INS error by half a GNSS interval (an error of rate·Δt/2: 30 m for the
seed-000 INS drifting at 60 m/s with 1 Hz GNSS); Tustin would warp the frequency axis and
forward Euler is unstable for ``h > 2T`` (T = 0.5 s in the first variable-structure stage
against a 1 s GNSS step). The matrix exponential is :func:`hil.nav.portable.expm` (scaling and
squaring of a Taylor series in plain arithmetic), not scipy's, whose BLAS calls round
differently on different CPUs. Discretisations are cached per (filter, step in integer ns), so
the 400 Hz path is one small matrix product per step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hil.nav.portable import c_einsum, expm, mv
from hil.nav.types import F64


@dataclass(frozen=True)
class TransferFunction:
    """``F(p) = num(p) / den(p)``, coefficients highest power first, p in 1/s."""

    num: tuple[float, ...]
    den: tuple[float, ...]
    label: str = ""

    def dc_gain(self) -> float:
        """F(0) = num(0) / den(0)."""
        return float(self.num[-1] / self.den[-1])

    def complement(self) -> TransferFunction:
        """``1 − F(p) = (den − num) / den``: what the compensation scheme applies to INS error."""
        den = np.asarray(self.den, dtype=float)
        num = np.zeros_like(den)
        num[len(den) - len(self.num) :] = self.num
        return TransferFunction(tuple(np.trim_zeros(den - num, "f")), self.den, f"1-{self.label}")

    def freq_response(self, w_radps: F64) -> F64:
        """Complex ``F(jω)``."""
        s = 1j * np.asarray(w_radps, dtype=float)
        return np.polyval(self.num, s) / np.polyval(self.den, s)  # type: ignore[no-any-return]


@dataclass(frozen=True)
class StateSpace:
    """``ẋ = A x + B u, y = C x + D u`` for a single-input single-output filter."""

    a: F64  # (n, n)
    b: F64  # (n,)
    c: F64  # (n,)
    d: float

    @staticmethod
    def from_tf(tf: TransferFunction) -> StateSpace:
        """Controller canonical form, the same arithmetic as ``scipy.signal.tf2ss`` (bit for bit).

        Written out because importing ``scipy.signal`` costs seconds at every ``hil sim`` and
        rerun start, for four lines of algebra; tests/unit/test_lti_tf2ss.py holds it to scipy.
        """
        den = np.trim_zeros(np.asarray(tf.den, float), "f")
        num = np.asarray(tf.num, float) / den[0]
        den = den / den[0]
        lead = 0  # scipy's normalize: numerator leading |c| <= 1e-14 dropped, one kept
        while lead < len(num) - 1 and abs(num[lead]) <= 1e-14:
            lead += 1
        num = num[lead:]
        k = len(den)
        if len(num) > k:
            raise ValueError(f"improper transfer function {tf.label!r}: num is longer than den")
        if k == 1:
            return StateSpace(np.zeros((1, 1)), np.zeros(1), np.zeros(1), float(num[0]))
        num = np.concatenate((np.zeros(k - len(num)), num))
        a = np.vstack((-den[None, 1:], np.eye(k - 2, k - 1)))
        c = num[1:] - num[0] * den[1:]
        return StateSpace(a, np.eye(k - 1, 1)[:, 0].copy(), c, float(num[0]))

    @property
    def order(self) -> int:
        return int(self.a.shape[0])

    def observability(self) -> F64:
        """Rows ``C A^k``, k = 0..n−1: maps the state to the output and its derivatives."""
        rows = [self.c]
        for _ in range(self.order - 1):
            rows.append(mv(self.a.T, rows[-1]))  # row C A^k
        return np.vstack(rows)


def zoh(ss: StateSpace, h_s: float) -> tuple[F64, F64]:
    """Exact ZOH discretisation over ``h_s``: returns ``(Φ, Γ)`` with ``x+ = Φ x + Γ u``."""
    from scipy import signal  # seconds to import; only tests and benches call this

    n = ss.order
    ad, bd, _, _, _ = signal.cont2discrete(
        (ss.a, ss.b.reshape(n, 1), ss.c.reshape(1, n), np.array([[ss.d]])), h_s, method="zoh"
    )
    return np.asarray(ad, float), np.asarray(bd, float)[:, 0].copy()


def ramp_hold(ss: StateSpace, h_s: float) -> tuple[F64, F64, F64]:
    """Exact discretisation for a ramp input ``u(τ) = u0 + s τ`` over ``h_s``.

    ``x+ = Φ x + Γ0 u0 + Γ1 s`` from ``expm([[A, B, 0], [0, 0, 1], [0, 0, 0]] h)`` (the input
    and its slope appended as states). ``Γ0`` equals the ZOH ``Γ`` of ``cont2discrete``.
    """
    n = ss.order
    e = _ramp_expm(ss, h_s)
    return e[:n, :n].copy(), e[:n, n].copy(), e[:n, n + 1].copy()


def _ramp_expm(ss: StateSpace, h_s: float) -> F64:
    """``expm([[A, B, 0], [0, 0, 1], [0, 0, 0]] h)``: its first ``n`` rows are ``[Φ | Γ0 | Γ1]``."""
    n = ss.order
    m = np.zeros((n + 2, n + 2))
    m[:n, :n] = ss.a
    m[:n, n] = ss.b
    m[n, n + 1] = 1.0
    return expm(m * h_s)  # type: ignore[no-any-return]  # portable: the same bits on any machine


def held_noise_gain(tf: TransferFunction, hold_s: float) -> float:
    """RMS of ``F``'s output per unit σ of white noise sampled every ``hold_s`` and held.

    The held noise has the two-sided spectrum ``σ² h sinc²(f h)``, so the output variance is
    ``σ² h ∫ |F(j2πf)|² sinc²(f h) df`` over all f: the floor a compensation filter leaves from
    the GNSS white noise alone, whatever the INS does (``F`` passes it, ``1 − F`` does not enter).
    Integrated numerically to 200/h Hz: for a strictly proper low-pass ``F`` (every compensation
    and complementary filter here) the integrand there is below 1e-13 of its peak.
    """
    h = float(hold_s)
    f = np.linspace(0.0, 200.0 / h, 2_000_001)
    g = np.abs(tf.freq_response(2.0 * np.pi * f)) ** 2 * np.sinc(f * h) ** 2
    return float(np.sqrt(2.0 * h * np.trapezoid(g, f)))


@dataclass
class ZohCache:
    """``(Φ, Γ0, Γ1)`` per step length in integer ns, so equal steps never recompute ``e^{A h}``."""

    ss: StateSpace
    max_entries: int = 256
    ramp: bool = True  # whether :meth:`stacked` carries Γ1 (a coast's input has no slope)
    _table: dict[int, tuple[F64, F64, F64]] = field(default_factory=dict)
    _stacked: dict[int, F64] = field(default_factory=dict)

    def get(self, h_ns: int) -> tuple[F64, F64, F64]:
        hit = self._table.get(h_ns)
        if hit is None:
            if len(self._table) >= self.max_entries:
                # Jittery steps would otherwise grow the table without bound; evicting the
                # oldest entry costs at worst one recomputation of e^{A h}.
                self._table.pop(next(iter(self._table)))
            hit = ramp_hold(self.ss, h_ns * 1e-9)
            self._table[h_ns] = hit
        return hit

    def stacked(self, h_ns: int) -> F64:
        """``[Φ | Γ0 | Γ1]`` (n, n + 2; without ``Γ1`` unless ``ramp``) for :func:`stacked_step`,
        cached like :meth:`get`."""
        hit = self._stacked.get(h_ns)
        if hit is None:
            if len(self._stacked) >= self.max_entries:
                self._stacked.pop(next(iter(self._stacked)))
            n = self.ss.order  # ramp_hold's matrices side by side: the first n rows of its e^{M h}
            cols = n + (2 if self.ramp else 1)
            hit = _ramp_expm(self.ss, h_ns * 1e-9)[:n, :cols].copy()
            self._stacked[h_ns] = hit
        return hit


_SHARED: dict[tuple[bytes, bytes, tuple[int, ...], bool], ZohCache] = {}


def shared_zoh_cache(ss: StateSpace, ramp: bool = True) -> ZohCache:
    """The process's one :class:`ZohCache` of the filter ``ss``: estimators running the same
    filter (comp3f and compvs's last stage, say) compute each step's ``e^{A h}`` once. Its
    entries are a function of ``(A, B, h)`` alone, so sharing changes no bit."""
    key = (ss.a.tobytes(), ss.b.tobytes(), ss.a.shape, ramp)
    cache = _SHARED.get(key)
    if cache is None:
        if len(_SHARED) >= 64:  # filters built with ever new parameters (tests, sweeps)
            _SHARED.pop(next(iter(_SHARED)))
        cache = _SHARED[key] = ZohCache(ss, ramp=ramp)
    return cache


def stacked_step(m: F64, x: F64, *rows: F64) -> F64:
    """``M [x; r1; r2; …]``: ``Φ x + Γ0 u + Γ1 s`` for ``M = [Φ | Γ0 | Γ1]`` and rows ``u, s``
    (one per channel), as one product instead of a product and two outer products.

    The same bits: einsum sums ``j`` in order, so the product's terms come in the order the
    separate expression adds them (Φ x first, then Γ0 u, then Γ1 s); held to that on random
    matrices of the filters' orders in tests/unit/test_lti_stacked.py.
    """
    return c_einsum("ij,jk->ik", m, np.concatenate((x, *[r[None, :] for r in rows])))  # type: ignore[no-any-return]


def aperiodic(order: int, t_s: float) -> TransferFunction:
    """``1 / (T p + 1)^order``: the classic aperiodic (first-order lag) cascade."""
    den = np.poly1d([t_s, 1.0]) ** order
    return TransferFunction((1.0,), tuple(float(c) for c in den.coeffs), f"1/({t_s:g}p+1)^{order}")


def forcing3(t_s: float) -> TransferFunction:
    """``(3 T p + 1) / (T p + 1)^3``: the seed-000 third-order filter with forcing.

    ``1 − F = T² p² (T p + 3) / (T p + 1)^3`` has a double zero at p = 0, so constant and
    linearly growing INS errors are removed in steady state.
    """
    den = np.poly1d([t_s, 1.0]) ** 3
    return TransferFunction(
        (3.0 * t_s, 1.0), tuple(float(c) for c in den.coeffs), f"({3 * t_s:g}p+1)/({t_s:g}p+1)^3"
    )


def complementary2(r1: float, r2: float) -> TransferFunction:
    """Seed 003: ``W(s) = (r1 s + r2) / (s² + r1 s + r2)``; ``1 − W = s² / (…)``."""
    return TransferFunction((r1, r2), (1.0, r1, r2), f"cf2(r1={r1:g},r2={r2:g})")


def complementary3(k1: float, k2: float, k3: float) -> TransferFunction:
    """Seed 003: ``W(s) = (k1 s² + k2 s + k3) / (s³ + k1 s² + k2 s + k3)``; ``1 − W = s³/(…)``."""
    return TransferFunction((k1, k2, k3), (1.0, k1, k2, k3), f"cf3(k1={k1:g},k2={k2:g},k3={k3:g})")
