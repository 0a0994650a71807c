"""Compiled core of the simulator: the TEM heat terms and a stiff integrator.

Everything here is numba-compiled and works on plain arrays; the readable
model (rig descriptions, laws, effects) lives in :mod:`tembayes.physics.rig`,
:mod:`tembayes.physics.tem` and :mod:`tembayes.physics.effects`, and
:mod:`tembayes.physics.simulate` turns it into these arrays.

The state is the vector of node temperatures [K] of a thermal network:

    C_i dT_i/dt = sum_j G_ij (T_j - T_i) + sum_b Gb_ib (T_b - T_i) + Q_i(T, I)

written as ``dT/dt = A T + Bb u_b + Cinv * Q`` with ``A`` and ``Bb`` built once
per parameter draw.  ``Q`` is the heat the thermoelectric module releases into
its nodes: a chain ``tem_nodes = (hot plate, leg cells..., cold plate)``.
With no leg cells this is exactly the paper's lumped element (eqs 4-5);
leg cells give the virtual bench's higher-fidelity module.

The integrator is Shampine & Reichelt's modified Rosenbrock pair (MATLAB's
``ode23s``): L-stable, so the plates (tau ~ 0.1 s) and the blocks (minutes)
are both handled, with an embedded error estimate for step control.  Inputs
(current and the measured boundary temperatures) are linear between samples, and the
steps land exactly on every sample time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit, prange

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, DTypeLike

# Index of each coefficient in a TEM parameter vector ``p``.  Every effect
# coefficient is zero in the paper's model.
P_R0, P_R1, P_R2 = 0, 1, 2  # R = R0 + R1 x + R2 x^2 [ohm], x = T - T_ref [K]
P_S0, P_S1, P_S2 = 3, 4, 5  # S = S0 + S1 x + S2 x^2 [V/K]
P_K0, P_K1 = 6, 7  # K = K0 (1 + K1 x) [W/K], K1 relative [1/K]
P_THOMSON = 8  # 0: S(T_mean) at both junctions; 1: own S at each junction + Thomson heat (linear blend)
P_JOULE = 9  # excess fraction of Joule heat released at the hot side (0 = equal split)
P_IGAIN = 10  # measured current = (1 + gain) I + offset
P_IOFFSET = 11  # [A]
P_TREF = 12  # reference temperature of the laws [K]
N_P = 13

_SQRT2 = np.sqrt(2.0)
_D = 1.0 / (2.0 + _SQRT2)
_E32 = 6.0 + _SQRT2
_HC = 1e-20  # complex-step size: derivative exact to rounding, no cancellation
#: Step budget: a parameter set so stiff or unstable that the integrator needs
#: more than ``MAX_STEPS_PER_POINT`` steps per output point on average (plus
#: ``MIN_STEP_BUDGET``; typical runs take 1-3 per point) is given up, not ground
#: through for hours (``stats[3] = 2``, outputs NaN from there on).  Seen when an
#: optimiser probes far outside the priors: 29 million steps, 109 s, before.
MAX_STEPS_PER_POINT = 20
MIN_STEP_BUDGET = 10000


@njit(cache=True)
def _poly(p, i, x):
    return p[i] + p[i + 1] * x + p[i + 2] * x * x


@njit(cache=True)
def _resistance_t(T, k, p):
    """Temperature [K] at which leg cell ``k`` of the chain ``T`` resists (and releases its Joule heat).

    The cells of :func:`tem_heat` are joined to the junctions by half a
    cell's conductance, so under a uniform heat source (Joule, and Thomson
    heat at a near-linear profile) each runs a constant ``q / (8 n^2 K)``
    above the continuous leg at its centre: their mean departure from the
    junctions' straight line is ``1 + 2/n^2`` times the continuum's.  The
    departure is scaled back to the continuum's.  It is taken in the
    Kirchhoff variable ``u = x + K1 x^2 / 2`` (``x = T - T_ref``), in which
    the segments' conduction is exactly linear, so a curve that K(T) alone
    makes (exact at the cells already) is left as it is; ``u`` is turned
    back into T by the root that is ``u`` at ``K1 = 0``.  Heat and voltage
    read the same temperatures: the first law stays exact.
    """
    n = T.shape[0] - 2
    tref = p[P_TREF]
    k1 = p[P_K1]
    w = (k - 0.5) / n
    u0 = _kirchhoff(T[0] - tref, k1)
    line = u0 + (_kirchhoff(T[n + 1] - tref, k1) - u0) * w
    u = line + (_kirchhoff(T[k] - tref, k1) - line) / (1.0 + 2.0 / (n * n))
    return tref + 2.0 * u / (1.0 + np.sqrt(1.0 + 2.0 * k1 * u))


@njit(cache=True)
def _kirchhoff(x, k1):
    return x + 0.5 * k1 * x * x


@njit(cache=True)
def tem_heat(T: np.ndarray, I: float | complex, p: np.ndarray, Q: np.ndarray) -> None:
    """Heat released by the module into its chain of nodes.

    Parameters
    ----------
    T : ndarray, shape (m,)
        Temperatures of (hot plate, leg cells..., cold plate) [K]; real or
        complex (complex for complex-step derivatives).
    I : float or complex
        True module current [A]; positive cools the cold plate.
    p : ndarray, shape (N_P,)
        TEM parameter vector (see the ``P_*`` indices).
    Q : ndarray, shape (m,)
        Output: heat into each node [W].
    """
    m = T.shape[0]
    n_leg = m - 2
    tref = p[P_TREF]
    Th = T[0]
    Tc = T[m - 1]
    Tm = 0.5 * (Th + Tc)
    x = Tm - tref
    lam = p[P_THOMSON]
    delta = p[P_JOULE]
    I2 = I * I
    for k in range(m):
        Q[k] = 0.0 * T[k]
    # Peltier heat at the junctions: S(T_mean) (the paper) at lam = 0, each
    # junction's own S at lam = 1, linear in between.
    Sm = _poly(p, P_S0, x)
    Sh = (1.0 - lam) * Sm + lam * _poly(p, P_S0, Th - tref)
    Sc = (1.0 - lam) * Sm + lam * _poly(p, P_S0, Tc - tref)
    Q[0] += Sh * Th * I
    Q[m - 1] -= Sc * Tc * I
    # Joule heat: equal split (paper) unless delta moves part of it to one
    # side, as a contact resistance on that side would.
    Rm = _poly(p, P_R0, x)
    if n_leg == 0:
        Q[0] += (0.5 + delta) * Rm * I2
        Q[1] += (0.5 - delta) * Rm * I2
    else:
        if delta >= 0.0:
            Q[0] += 2.0 * delta * Rm * I2
            frac = 1.0 - 2.0 * delta
        else:
            Q[m - 1] -= 2.0 * delta * Rm * I2
            frac = 1.0 + 2.0 * delta
        for k in range(1, m - 1):
            Q[k] += frac * _poly(p, P_R0, _resistance_t(T, k, p) - tref) / n_leg * I2
    # Fourier conduction and Thomson heat, segment by segment.
    for j in range(m - 1):
        if n_leg == 0:
            w = 1.0
        elif j == 0 or j == m - 2:
            w = 2.0 * n_leg
        else:
            w = 1.0 * n_leg
        Ts = 0.5 * (T[j] + T[j + 1])
        xs = Ts - tref
        dT = T[j] - T[j + 1]
        q = w * p[P_K0] * (1.0 + p[P_K1] * xs) * dT
        Q[j] -= q
        Q[j + 1] += q
        # Thomson heat T dS/dT I dT of the segment, written as
        # d(S T) - S dT so that it telescopes with the junction terms: the
        # heat released then equals V I exactly for any law shape.
        qt = (
            -lam
            * I
            * (
                _poly(p, P_S0, T[j] - tref) * T[j]
                - _poly(p, P_S0, T[j + 1] - tref) * T[j + 1]
                - _poly(p, P_S0, xs) * dT
            )
        )
        Q[j] += 0.5 * qt
        Q[j + 1] += 0.5 * qt


@njit(cache=True)
def tem_voltage(T: np.ndarray, I: float | complex, p: np.ndarray) -> float | complex:
    """Module terminal voltage [V] for the chain temperatures ``T`` [K] and true current ``I`` [A].

    ``V = R I + V_seebeck`` with the paper's ``V_seebeck = S(T_mean) (Th - Tc)``
    (eq 9), blended towards the integral of S along the legs when the
    ``thomson`` coefficient is on.
    """
    m = T.shape[0]
    n_leg = m - 2
    tref = p[P_TREF]
    Th = T[0]
    Tc = T[m - 1]
    x = 0.5 * (Th + Tc) - tref
    lam = p[P_THOMSON]
    Rm = _poly(p, P_R0, x)
    if n_leg == 0:
        Rt = Rm
    else:
        delta = abs(p[P_JOULE])
        s = 0.0
        for k in range(1, m - 1):
            s += _poly(p, P_R0, _resistance_t(T, k, p) - tref)
        Rt = (1.0 - 2.0 * delta) * s / n_leg + 2.0 * delta * Rm
    vs = 0.0
    for j in range(m - 1):
        vs += _poly(p, P_S0, 0.5 * (T[j] + T[j + 1]) - tref) * (T[j] - T[j + 1])
    vs = (1.0 - lam) * _poly(p, P_S0, x) * (Th - Tc) + lam * vs
    return Rt * I + vs


@njit(cache=True)
def true_current(i_meas: float | np.ndarray, p: np.ndarray) -> float | np.ndarray:
    """True current [A] behind a measured current [A] (``current_offset`` effect)."""
    return (i_meas - p[P_IOFFSET]) / (1.0 + p[P_IGAIN])


@njit(cache=True)
def _boundary_term(Bb, i, u):
    """``sum_k Bb[i, k] u[k]``: node ``i``'s drive from the boundaries ``u`` (or their slopes)."""
    s = Bb[i, 0] * u[0]
    for k in range(1, u.shape[0]):
        s += Bb[i, k] * u[k]
    return s


@njit(cache=True)
def _boundaries_at(U, mb, n, t, ub):
    """The boundaries ``t`` seconds into sampling interval ``n``, linear between samples (into ``ub``)."""
    for k in range(ub.shape[0]):
        ub[k] = U[k, n] + mb[k] * t


@njit(cache=True)
def _rhs(y, I, ub, A, Bb, Cinv, tem, p, Tt, Qt, f):
    N = y.shape[0]
    m = tem.shape[0]
    for i in range(N):
        s = _boundary_term(Bb, i, ub)
        for j in range(N):
            s += A[i, j] * y[j]
        f[i] = s
    for k in range(m):
        Tt[k] = y[tem[k]]
    tem_heat(Tt, I, p, Qt)
    for k in range(m):
        f[tem[k]] += Cinv[tem[k]] * Qt[k]


@njit(cache=True)
def _jac(y, I, dI, A, Cinv, tem, p, Tz, Qz, J, dfdI):
    """State Jacobian ``J`` and ``dfdI`` (derivative w.r.t. current) by complex step."""
    N = y.shape[0]
    m = tem.shape[0]
    for i in range(N):
        dfdI[i] = 0.0
        for j in range(N):
            J[i, j] = A[i, j]
    for k in range(m):
        for r in range(m):
            Tz[r] = y[tem[r]] + 0j
        Tz[k] += 1j * _HC
        tem_heat(Tz, I + 0j, p, Qz)
        for r in range(m):
            J[tem[r], tem[k]] += Cinv[tem[r]] * Qz[r].imag / _HC
    if dI != 0.0:
        for r in range(m):
            Tz[r] = y[tem[r]] + 0j
        tem_heat(Tz, I + 1j * _HC, p, Qz)
        for r in range(m):
            dfdI[tem[r]] = Cinv[tem[r]] * Qz[r].imag / _HC


@njit(cache=True)
def _lu(W, piv):
    """In-place LU with partial pivoting of a small dense matrix."""
    n = W.shape[0]
    for k in range(n):
        im = k
        vm = abs(W[k, k])
        for i in range(k + 1, n):
            if abs(W[i, k]) > vm:
                vm = abs(W[i, k])
                im = i
        piv[k] = im
        if im != k:
            for j in range(n):
                tmp = W[k, j]
                W[k, j] = W[im, j]
                W[im, j] = tmp
        inv = 1.0 / W[k, k]
        for i in range(k + 1, n):
            W[i, k] *= inv
            lik = W[i, k]
            for j in range(k + 1, n):
                W[i, j] -= lik * W[k, j]


@njit(cache=True)
def _lusolve(W, piv, b):
    n = W.shape[0]
    for k in range(n):
        if piv[k] != k:
            tmp = b[k]
            b[k] = b[piv[k]]
            b[piv[k]] = tmp
    for i in range(n):
        s = b[i]
        for j in range(i):
            s -= W[i, j] * b[j]
        b[i] = s
    for i in range(n - 1, -1, -1):
        s = b[i]
        for j in range(i + 1, n):
            s -= W[i, j] * b[j]
        b[i] = s / W[i, i]


@njit(cache=True)
def _steady(y, I, ub, A, Bb, Cinv, tem, p, Tt, Qt, Tz, Qz, f, J, dfdI, piv):
    """Newton iterations to the steady state at constant inputs (in place)."""
    N = y.shape[0]
    for _it in range(60):
        _rhs(y, I, ub, A, Bb, Cinv, tem, p, Tt, Qt, f)
        _jac(y, I, 0.0, A, Cinv, tem, p, Tz, Qz, J, dfdI)
        _lu(J, piv)
        for i in range(N):
            f[i] = -f[i]
        _lusolve(J, piv, f)
        mx = 0.0
        for i in range(N):
            y[i] += f[i]
            mx = max(mx, abs(f[i]))
        if mx < 1e-11:
            return True
    return False


@njit(cache=True)
def _integrate_one(t, i_meas, U, A, Bb, Cinv, tem, p, rec, y, steady_start, atol, hmax, out, vout, stats):
    N = y.shape[0]
    m = tem.shape[0]
    nt = t.shape[0]
    nr = rec.shape[0]
    nb = U.shape[0]
    ub = np.empty(nb)  # boundary temperatures at a stage [K]
    mb = np.empty(nb)  # their slopes over the sampling interval [K/s]
    Tt = np.empty(m)
    Qt = np.empty(m)
    Tz = np.empty(m, dtype=np.complex128)
    Qz = np.empty(m, dtype=np.complex128)
    F0 = np.empty(N)
    F1 = np.empty(N)
    F2 = np.empty(N)
    k1 = np.empty(N)
    k2 = np.empty(N)
    k3 = np.empty(N)
    yn = np.empty(N)
    ytmp = np.empty(N)
    J = np.empty((N, N))
    W = np.empty((N, N))
    dfdI = np.empty(N)
    dfdt = np.empty(N)
    piv = np.empty(N, dtype=np.int64)

    I0 = true_current(i_meas[0], p)
    if steady_start:
        ub[:] = U[:, 0]
        ok = _steady(y, I0, ub, A, Bb, Cinv, tem, p, Tt, Qt, Tz, Qz, F0, J, dfdI, piv)
        if not ok:
            stats[3] = 1.0
    for r in range(nr):
        out[0, r] = y[rec[r]]
    for k in range(m):
        Tt[k] = y[tem[k]]
    vout[0] = tem_voltage(Tt, I0, p)

    h = hmax
    nsteps = 0
    nrej = 0
    ub[:] = U[:, 0]
    _rhs(y, I0, ub, A, Bb, Cinv, tem, p, Tt, Qt, F0)
    for n in range(nt - 1):
        dt = t[n + 1] - t[n]
        Ia = true_current(i_meas[n], p)
        Ib = true_current(i_meas[n + 1], p)
        mI = (Ib - Ia) / dt
        for k in range(nb):
            mb[k] = (U[k, n + 1] - U[k, n]) / dt
        s = 0.0  # time into the interval
        h = min(h, hmax)
        budget = MAX_STEPS_PER_POINT * (n + 1) + MIN_STEP_BUDGET
        while s < dt:
            if nsteps + nrej > budget:
                stats[3] = 2.0
                break
            last = False
            # stretch the step up to 1 % to land on the sample rather than
            # leave a sliver (float sample times are rarely exact multiples)
            if s + 1.01 * h >= dt:
                h = dt - s
                last = True
            # inputs and their time derivative at the start of the step
            I_s = Ia + mI * s
            _jac(y, I_s, mI, A, Cinv, tem, p, Tz, Qz, J, dfdI)
            for i in range(N):
                dfdt[i] = _boundary_term(Bb, i, mb) + dfdI[i] * mI
            while True:
                hd = h * _D
                for i in range(N):
                    for j in range(N):
                        W[i, j] = -hd * J[i, j]
                    W[i, i] += 1.0
                _lu(W, piv)
                for i in range(N):
                    k1[i] = F0[i] + hd * dfdt[i]
                _lusolve(W, piv, k1)
                sh = s + 0.5 * h
                for i in range(N):
                    ytmp[i] = y[i] + 0.5 * h * k1[i]
                _boundaries_at(U, mb, n, sh, ub)
                _rhs(ytmp, Ia + mI * sh, ub, A, Bb, Cinv, tem, p, Tt, Qt, F1)
                for i in range(N):
                    k2[i] = F1[i] - k1[i]
                _lusolve(W, piv, k2)
                for i in range(N):
                    k2[i] += k1[i]
                    yn[i] = y[i] + h * k2[i]
                se = s + h
                _boundaries_at(U, mb, n, se, ub)
                _rhs(yn, Ia + mI * se, ub, A, Bb, Cinv, tem, p, Tt, Qt, F2)
                for i in range(N):
                    k3[i] = F2[i] - _E32 * (k2[i] - F1[i]) - 2.0 * (k1[i] - F0[i]) + hd * dfdt[i]
                _lusolve(W, piv, k3)
                err = 0.0
                for i in range(N):
                    e = abs(h / 6.0 * (k1[i] - 2.0 * k2[i] + k3[i])) / atol
                    if e > err:
                        err = e
                if err <= 1.0:
                    break
                nrej += 1
                h = h * max(0.2, 0.8 * err ** (-1.0 / 3.0))
                last = False
                if nrej > budget or not (h > 0.0):
                    stats[3] = 2.0
                    break
            if stats[3] == 2.0:
                break
            nsteps += 1
            for i in range(N):
                y[i] = yn[i]
                F0[i] = F2[i]
            s = s + h if not last else dt
            fac = 5.0 if err < 1e-6 else min(5.0, 0.8 * err ** (-1.0 / 3.0))
            hnew = h * max(0.2, fac)
            if not last:
                h = hnew
            else:
                # keep the step that the error allowed for the next interval
                h = max(h, min(hnew, hmax))
        if stats[3] == 2.0:
            for j in range(n + 1, nt):
                vout[j] = np.nan
                for r in range(nr):
                    out[j, r] = np.nan
            break
        for r in range(nr):
            out[n + 1, r] = y[rec[r]]
        for k in range(m):
            Tt[k] = y[tem[k]]
        vout[n + 1] = tem_voltage(Tt, Ib, p)
    stats[0] = nsteps
    stats[1] = nrej


def writable(a: ArrayLike, dtype: DTypeLike = None) -> np.ndarray:
    """``a`` as the compiled entry points take it: C-contiguous and writable.

    A read-only or strided array is a different numba type, and so another
    compiled version of the entry point; with ``cache=True`` a second version
    loaded back from the on-disk cache crashed the process (segmentation fault,
    numba 0.68, the parallel integrator).  Every Python caller therefore hands
    the kernel one array type; a read-only array (``Experiment`` columns) is
    copied, which is cheap next to the integration.
    """
    return np.require(a, dtype=dtype, requirements=("C", "W"))


def _kernel_args(t, i_meas, U, A, Bb, Cinv, tem, P, rec, Y0, steady_start, atol, hmax):
    """The integrators' arguments as their one compiled signature takes them (see :func:`writable`)."""
    f, i = np.float64, np.int64
    return (
        writable(t, f),
        writable(i_meas, f),
        writable(U, f),
        writable(A),
        writable(Bb),
        writable(Cinv),
        writable(tem, i),
        writable(P),
        writable(rec, i),
        writable(Y0, f),
        bool(steady_start),
        float(atol),
        float(hmax),
    )


def integrate(*args) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulate ``nd`` parameter draws of one experiment (see :func:`_integrate`)."""
    return _integrate(*_kernel_args(*args))


def integrate_grids(*args) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`integrate` with a time grid and inputs of its own for every draw (see :func:`_integrate_grids`)."""
    return _integrate_grids(*_kernel_args(*args))


@njit(cache=True)
def _integrate(t, i_meas, U, A, Bb, Cinv, tem, P, rec, Y0, steady_start, atol, hmax):
    """Simulate ``nd`` parameter draws of one experiment.

    Parameters
    ----------
    t : ndarray, shape (nt,)
        Sample times [s], strictly increasing.
    i_meas : ndarray, shape (nt,)
        Measured current [A], linear between samples.
    U : ndarray, shape (nb, nt)
        Measured boundary temperatures [K] in the rig's boundary order,
        linear between samples.
    A : ndarray, shape (nd, N, N)
        Linear network matrix [1/s].
    Bb : ndarray, shape (nd, N, nb)
        Boundary input matrix [1/s].
    Cinv : ndarray, shape (nd, N)
        Inverse node capacitances [K/J].
    tem : ndarray of int64, shape (m,)
        Node indices of (hot plate, leg cells..., cold plate).
    P : ndarray, shape (nd, N_P)
        TEM parameter vectors.
    rec : ndarray of int64, shape (nr,)
        Node indices to record.
    Y0 : ndarray, shape (nd, N)
        Initial state [K]; refined to the steady state at the first sample's
        inputs when ``steady_start``.
    steady_start : bool
    atol : float
        Absolute local error tolerance [K].
    hmax : float
        Largest internal step [s].

    Returns
    -------
    out : ndarray, shape (nd, nt, nr)
        Recorded node temperatures [K].
    volt : ndarray, shape (nd, nt)
        Terminal voltage [V].
    stats : ndarray, shape (nd, 4)
        Accepted steps, rejected steps, unused, steady-start failure flag.
    """
    nd = P.shape[0]
    nt = t.shape[0]
    # one grid for every draw: stride-0 views, no copies
    T = np.broadcast_to(t, (nd, nt))
    return _integrate_grids(
        T,
        np.broadcast_to(i_meas, (nd, nt)),
        np.broadcast_to(U, (nd,) + U.shape),
        A,
        Bb,
        Cinv,
        tem,
        P,
        rec,
        Y0,
        steady_start,
        atol,
        hmax,
    )


@njit(cache=True, parallel=True)
def _integrate_grids(T, I, U, A, Bb, Cinv, tem, P, rec, Y0, steady_start, atol, hmax):
    """:func:`_integrate` with a time grid and inputs of its own for every draw.

    Same as :func:`integrate` except ``T`` and ``I`` have shape ``(nd, nt)``
    and ``U`` shape ``(nd, nb, nt)``: the calibration moves each draw's current steps to its own
    instant within the sampling interval.
    """
    nd = P.shape[0]
    nt = T.shape[1]
    nr = rec.shape[0]
    out = np.empty((nd, nt, nr))
    volt = np.empty((nd, nt))
    stats = np.zeros((nd, 4))
    for d in prange(nd):
        y = Y0[d].copy()
        _integrate_one(
            T[d],
            I[d],
            U[d],
            A[d],
            Bb[d],
            Cinv[d],
            tem,
            P[d],
            rec,
            y,
            steady_start,
            atol,
            hmax,
            out[d],
            volt[d],
            stats[d],
        )
    return out, volt, stats


@njit(cache=True)
def rhs_one(
    y: np.ndarray,
    I: float,
    ub: np.ndarray,
    A: np.ndarray,
    Bb: np.ndarray,
    Cinv: np.ndarray,
    tem: np.ndarray,
    p: np.ndarray,
) -> np.ndarray:
    """Right-hand side ``dT/dt`` [K/s] for one draw (used by the scipy reference and tests)."""
    m = tem.shape[0]
    f = np.empty(y.shape[0])
    _rhs(y, I, ub, A, Bb, Cinv, tem, p, np.empty(m), np.empty(m), f)
    return f


@njit(cache=True)
def jac_one(y: np.ndarray, I: float, A: np.ndarray, Cinv: np.ndarray, tem: np.ndarray, p: np.ndarray) -> np.ndarray:
    """State Jacobian [1/s] for one draw (used by the scipy reference and tests)."""
    N = y.shape[0]
    m = tem.shape[0]
    J = np.empty((N, N))
    _jac(y, I, 0.0, A, Cinv, tem, p, np.empty(m, dtype=np.complex128), np.empty(m, dtype=np.complex128), J, np.empty(N))
    return J


@njit(cache=True)
def steady_one(
    y0: np.ndarray,
    I: float,
    ub: np.ndarray,
    A: np.ndarray,
    Bb: np.ndarray,
    Cinv: np.ndarray,
    tem: np.ndarray,
    p: np.ndarray,
) -> tuple[np.ndarray, bool]:
    """Steady state [K] at constant inputs for one draw, from the guess ``y0``."""
    N = y0.shape[0]
    m = tem.shape[0]
    y = y0.copy()
    ok = _steady(
        y,
        I,
        ub,
        A,
        Bb,
        Cinv,
        tem,
        p,
        np.empty(m),
        np.empty(m),
        np.empty(m, dtype=np.complex128),
        np.empty(m, dtype=np.complex128),
        np.empty(N),
        np.empty((N, N)),
        np.empty(N),
        np.empty(N, dtype=np.int64),
    )
    return y, ok


@njit(cache=True)
def first_order_lag(time: np.ndarray, Y: np.ndarray, tau: np.ndarray) -> None:
    """First-order lag ``y' = (u - y) / tau`` of sampled signals, in place.

    Exact for inputs linear between samples (uneven sampling allowed).

    Parameters
    ----------
    time : ndarray, shape (nd, nt)
        Each draw's sample times [s] (a draw's step points move with its own step shift).
    Y : ndarray, shape (nd, nch, nt)
        Signals; replaced by the lagged ones.  Signals with ``tau <= 0`` are left alone.
    tau : ndarray, shape (nd, nch)
        Each draw's and channel's time constant [s].
    """
    nd, nch, nt = Y.shape
    for d in range(nd):
        for c in range(nch):
            tc = tau[d, c]
            if tc <= 0.0:
                continue
            u_prev = Y[d, c, 0]
            y = u_prev
            for n in range(nt - 1):
                h = time[d, n + 1] - time[d, n]
                u = Y[d, c, n + 1]
                m = (u - u_prev) / h
                a = np.exp(-h / tc)
                y = u - m * tc + (y - u_prev + m * tc) * a
                Y[d, c, n + 1] = y
                u_prev = u
