"""Compiled (numba) hot paths: the module likelihood terms and the sampler's prior.

Arrays follow one layout throughout: ``W`` hyperparameter points (walkers),
``N`` modules, ``D`` = 5 parameters in population coordinates ``x``
(:mod:`.model`).  ``lw`` (W, 3) holds the per-parameter log weights of the
member, moderate and gross components; ``lam`` the moderate component's
width in spreads; ``gm, gs`` (D,) the gross component's mean and sd.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from tembayes.calibrate.population.model import BOX_SDS, LOGIT_F_MAX

#: Below this ratio (e^-3) a parameter's off patterns enter the Gaussian terms
#: in product form instead of being summed over exactly (error ~ rho^2).
RHO_EXACT = math.exp(-3.0)
#: A log ratio above this could overflow ``exp``: the parameter counts as infinitely off.
_LOG_RATIO_MAX = 500.0
#: Squared z below which the importance sums' three densities cannot underflow.
_Z2_SAFE = 1400.0


@njit(cache=True)
def _logaddexp(a, b):
    if a == -np.inf:
        return b
    if a > b:
        return a + math.log1p(math.exp(b - a))
    return b + math.log1p(math.exp(a - b))


@njit(cache=True)
def _log_expit(x):
    return -math.log1p(math.exp(-x)) if x > 0 else x - math.log1p(math.exp(x))


# --------------------------------------------------------------------------- Gaussian terms


@njit(cache=True)
def _rho_parts(pkk, uk, d, c, lwdiff):
    """Ratio of "parameter k off" to the base pattern: rho = exp(a) / sqrt(g).

    The off component changes A_kk by ``d`` and the mean of x_k by ``c``
    (a rank-one update); with P = A^-1 and u = P r of the base pattern
    (``pkk = P_kk``, ``uk = u_k``): g = 1 + d P_kk and
    a = lwdiff - (-2 c u_k + c^2 P_kk - d (u_k - c P_kk)^2 / g) / 2.
    Returns (a, g); g <= 0 (impossible for a positive definite update) gives
    a = -inf.
    """
    g = 1.0 + d * pkk
    if not g > 0.0:
        return -np.inf, 1.0
    e = uk - c * pkk
    return lwdiff - 0.5 * (-2.0 * c * uk + c * c * pkk - d * e * e / g), g


@njit(cache=True)
def _ratios(L, lw, w, dm, dg, cg, Pst, ust, lr1, f_mask):
    """Ratios rho (linear) of the parameters not yet summed over in frame ``L``, into ``lr1[L]``.

    Two exp and two sqrt per parameter: the hot path.  Returns the largest
    ratio and its parameter (-1 if none is left).
    """
    best = -1.0
    kstar = -1
    for k in range(Pst.shape[1]):
        if (f_mask[L] >> k) & 1:
            continue
        a1, g1 = _rho_parts(Pst[L, k, k], ust[L, k], dm[k], 0.0, lw[w, 1] - lw[w, 0])
        a2, g2 = _rho_parts(Pst[L, k, k], ust[L, k], dg[k], cg[k], lw[w, 2] - lw[w, 0])
        if a1 < _LOG_RATIO_MAX and a2 < _LOG_RATIO_MAX:
            rho = math.exp(a1) / math.sqrt(g1) + math.exp(a2) / math.sqrt(g2)
        else:
            rho = np.inf
        lr1[L, k] = rho
        if rho > best:
            best = rho
            kstar = k
    return best, kstar


@njit(cache=True)
def _product_form(L, lr1, f_mask, f_base):
    """Log sum of frame ``L`` with its remaining parameters in product form, ``prod (1 + rho)``."""
    prod = 1.0
    for k in range(lr1.shape[1]):
        if not (f_mask[L] >> k) & 1:
            prod *= 1.0 + lr1[L, k]
    return f_base[L] + math.log(prod)


@njit(cache=True)
def _open_frame(L, kstar, lw, w, dm, dg, cg, Pst, ust, lr1, lr2):
    """The two log ratios of parameter ``kstar`` in frame ``L`` (exact for huge exponents)."""
    a1, g1 = _rho_parts(Pst[L, kstar, kstar], ust[L, kstar], dm[kstar], 0.0, lw[w, 1] - lw[w, 0])
    a2, g2 = _rho_parts(Pst[L, kstar, kstar], ust[L, kstar], dg[kstar], cg[kstar], lw[w, 2] - lw[w, 0])
    lr1[L, kstar] = a1 - 0.5 * math.log(g1)
    lr2[L, kstar] = a2 - 0.5 * math.log(g2)


@njit(cache=True)
def _push_child(L, s, kstar, dm, dg, cg, Pst, ust, lr1, lr2, f_mask, f_base):
    """Frame ``L + 1``: parameter ``kstar`` of frame ``L`` in state ``s`` (0 member, 1 moderate, 2 gross).

    Off, it changes A_k*k* by ``d`` and the mean of x_k* by ``c``: a rank-one
    update of P and u.
    """
    D = Pst.shape[1]
    c1 = L + 1
    f_mask[c1] = f_mask[L] | (1 << kstar)
    if s == 0:
        for a in range(D):
            ust[c1, a] = ust[L, a]
            for b in range(D):
                Pst[c1, a, b] = Pst[L, a, b]
        f_base[c1] = f_base[L]
        return
    d = dm[kstar] if s == 1 else dg[kstar]
    c = 0.0 if s == 1 else cg[kstar]
    pkk = Pst[L, kstar, kstar]
    den = 1.0 + d * pkk
    f = (ust[L, kstar] - c * pkk) / den
    for a in range(D):
        va = Pst[L, a, kstar]
        ust[c1, a] = ust[L, a] - c * va - d * va * f
        for b in range(D):
            Pst[c1, a, b] = Pst[L, a, b] - d * va * Pst[L, b, kstar] / den
    f_base[c1] = f_base[L] + (lr1[L, kstar] if s == 1 else lr2[L, kstar])


@njit(cache=True)
def _pattern_sum(ll0, lw, w, dm, dg, cg, Pst, ust, lr1, lr2, f_mask, f_base, f_kstar, f_state, f_total):
    """Log of the sum over all member/moderate/gross patterns of one module.

    Frame 0 holds the member pattern: log density ``ll0``, precision matrix
    ``Pst[0]`` and precision times residual ``ust[0]``.  In each frame the
    parameter that looks most off (largest ratio, :func:`_rho_parts`) is summed
    over exactly -- member, moderate, gross; child frames by rank-one
    updates of P and u -- until every remaining parameter's ratio is below
    :data:`RHO_EXACT`; those enter in product form.  A module off in one
    parameter costs one level, one off everywhere all 3^5 patterns.  A
    depth-first walk with an explicit stack (numba cannot cache recursive
    functions).
    """
    f_mask[0] = 0
    f_base[0] = ll0
    L = 0
    entering = True
    while True:
        if entering:
            entering = False
            best, kstar = _ratios(L, lw, w, dm, dg, cg, Pst, ust, lr1, f_mask)
            if kstar < 0 or best < RHO_EXACT:
                result = _product_form(L, lr1, f_mask, f_base)
                if L == 0:
                    return result
                L -= 1
                f_total[L] = _logaddexp(f_total[L], result)
                continue
            _open_frame(L, kstar, lw, w, dm, dg, cg, Pst, ust, lr1, lr2)
            f_kstar[L] = kstar
            f_state[L] = 0
            f_total[L] = -np.inf
        s = f_state[L]
        if s == 3:  # all three states of k* done
            result = f_total[L]
            if L == 0:
                return result
            L -= 1
            f_total[L] = _logaddexp(f_total[L], result)
            continue
        _push_child(L, s, f_kstar[L], dm, dg, cg, Pst, ust, lr1, lr2, f_mask, f_base)
        f_state[L] = s + 1
        L += 1
        entering = True


@njit(cache=True)
def _cholesky_solve(m, C, i, mu, tau, w, L, r, y):
    """Cholesky factor of A = C_i + diag(tau_w^2) into ``L``, and ``L^-1 r`` into ``y``, r = m_i - mu_w.

    Returns (ok, log det L, |y|^2); ok is False if A is not positive definite.
    """
    D = m.shape[1]
    logdet = 0.0
    for k in range(D):
        r[k] = m[i, k] - mu[w, k]
        for j in range(k):
            v = C[i, k, j]
            for l in range(j):
                v -= L[k, l] * L[j, l]
            L[k, j] = v / L[j, j]
        v = C[i, k, k] + tau[w, k] * tau[w, k]
        for l in range(k):
            v -= L[k, l] * L[k, l]
        if not v > 0.0:
            return False, 0.0, 0.0
        L[k, k] = math.sqrt(v)
        logdet += math.log(L[k, k])
        a = r[k]
        for l in range(k):
            a -= L[k, l] * y[l]
        y[k] = a / L[k, k]
    quad = 0.0
    for k in range(D):
        quad += y[k] * y[k]
    return True, logdet, quad


@njit(cache=True)
def _precision_frame(L, r, Pst, ust):
    """``L <- L^-1`` in place, then P = L^-T L^-1 into ``Pst[0]`` and u = P r into ``ust[0]``."""
    D = L.shape[0]
    for j in range(D):
        L[j, j] = 1.0 / L[j, j]
        for k in range(j + 1, D):
            v = 0.0
            for l in range(j, k):
                v -= L[k, l] * L[l, j]
            L[k, j] = v / L[k, k]  # L[k, k] is still the original diagonal here
    for a in range(D):
        for b in range(a, D):
            v = 0.0
            for k in range(b, D):
                v += L[k, a] * L[k, b]
            Pst[0, a, b] = v
            Pst[0, b, a] = v
    for a in range(D):
        v = 0.0
        for b in range(D):
            v += Pst[0, a, b] * r[b]
        ust[0, a] = v


@njit(cache=True)
def _gauss_one(m, C, i, mu, tau, w, lam, lw, gm, gs, L, r, y, dm, dg, cg, Pst, ust, lr1, lr2, fi, ff):
    """Marginal likelihood of module i at walker w for a Gaussian module likelihood N(m_i, C_i).

    Member pattern: N(m_i; mu, A), A = C_i + diag(tau^2).  "Parameter j off"
    changes A_jj (moderate: tau_j -> lam tau_j; gross: tau_j -> gs_j and mean
    mu_j -> gm_j), a rank-one update, so each pattern's ratio to its base is
    exact in closed form (:func:`_rho_parts`); :func:`_pattern_sum` sums them.
    The other arguments are work arrays.

    Returns (log L_i, log P(member in all parameters | ...)).
    """
    D = m.shape[1]
    ok, logdet, quad = _cholesky_solve(m, C, i, mu, tau, w, L, r, y)
    if not ok:
        return -np.inf, 0.0
    _precision_frame(L, r, Pst, ust)
    ll0 = D * lw[w, 0] - 0.5 * quad - logdet - 0.5 * D * math.log(2.0 * math.pi)
    for k in range(D):
        t2 = tau[w, k] * tau[w, k]
        dm[k] = (lam * lam - 1.0) * t2  # moderate: variance change, same mean
        dg[k] = gs[k] * gs[k] - t2  # gross: variance and mean change
        cg[k] = gm[k] - mu[w, k]
    total = _pattern_sum(ll0, lw, w, dm, dg, cg, Pst, ust, lr1, lr2, fi[0], ff[0], fi[1], fi[2], ff[1])
    if not math.isfinite(total):
        return -np.inf, 0.0
    return total, ll0 - total


@njit(cache=True)
def _gauss_chunk(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, t0, t1):
    """Gaussian terms of the (walker, module) pairs ``t0 <= t < t1`` (``t = w N + i``)."""
    D = m.shape[1]
    N = out_ll.shape[1]
    L = np.zeros((D, D))
    r = np.empty(D)
    y = np.empty(D)
    dm = np.empty(D)
    dg = np.empty(D)
    cg = np.empty(D)
    Pst = np.empty((D + 1, D, D))  # per stack frame: precision matrix, precision x residual
    ust = np.empty((D + 1, D))
    lr1 = np.empty((D + 1, D))
    lr2 = np.empty((D + 1, D))
    fi = np.zeros((3, D + 1), dtype=np.int64)  # frame mask, k*, state
    ff = np.zeros((2, D + 1))  # frame base, running total
    for t in range(t0, t1):
        w = t // N
        i = t % N
        a, b = _gauss_one(m, C, i, mu, tau, w, lam, lw, gm, gs, L, r, y, dm, dg, cg, Pst, ust, lr1, lr2, fi, ff)
        out_ll[w, i] = a
        out_lmem[w, i] = b


@njit(cache=True)
def gauss_terms_serial(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem):
    """Gaussian terms of every walker and module on one thread.

    ``m`` (N, D), ``C`` (N, D, D): module likelihoods as Gaussians in ``x``;
    ``mu, tau`` (W, D).  Writes ``log L`` and ``log P(member)`` into
    ``out_ll, out_lmem`` (W, N).
    """
    _gauss_chunk(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, 0, out_ll.size)


@njit(cache=True, parallel=True)
def gauss_terms_parallel(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, n_chunks):
    """:func:`gauss_terms_serial` in ``n_chunks`` parallel chunks."""
    T = out_ll.size
    for c in prange(n_chunks):
        _gauss_chunk(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, c * T // n_chunks, (c + 1) * T // n_chunks)


# --------------------------------------------------------------------------- importance sums


@njit(cache=True)
def _importance_chunk(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, t0, t1):
    """Importance sums over module draws (self-normalised weights exp(lw0)).

    out_ll[w, i] = log sum_m exp(lw0_m) p(x_m | alpha);
    out_lmem[w, i] = log of the member share of that sum.
    """
    N = out_ll.shape[1]
    D = x.shape[1]
    c0 = 0.5 * math.log(2.0 * math.pi)
    loglam = math.log(lam)
    logtau = np.empty(D)
    lgross = np.empty(D)
    for j in range(D):
        lgross[j] = -math.log(gs[j]) - c0
    for t in range(t0, t1):
        w = t // N
        i = t % N
        for j in range(D):
            logtau[j] = math.log(tau[w, j])
        # the three components' weights over their density's normalisation (linear space)
        k0 = math.exp(lw[w, 0] - c0)
        k1 = math.exp(lw[w, 1] - c0 - loglam)
        bm, am = -np.inf, 0.0  # streaming log-sum-exp: mixture
        bq, aq = -np.inf, 0.0  # member
        for k in range(start[i], start[i + 1]):
            smix = lw0[k]
            smem = lw0[k]
            for j in range(D):
                z = (x[k, j] - mu[w, j]) / tau[w, j]
                zg = (x[k, j] - gm[j]) / gs[j]
                a = lw[w, 0] - 0.5 * z * z - logtau[j] - c0
                smem += a
                if z * z < _Z2_SAFE and zg * zg < _Z2_SAFE:  # one log for the three terms
                    smix += math.log(
                        (k0 * math.exp(-0.5 * z * z) + k1 * math.exp(-0.5 * z * z / (lam * lam))) / tau[w, j]
                        + math.exp(lw[w, 2] - 0.5 * zg * zg + lgross[j])
                    )
                else:
                    zo = z / lam
                    b = lw[w, 1] - 0.5 * zo * zo - logtau[j] - loglam - c0
                    g = lw[w, 2] - 0.5 * zg * zg + lgross[j]
                    smix += _logaddexp(_logaddexp(a, b), g)
            bm, am = _stream_logsumexp(bm, am, smix)
            bq, aq = _stream_logsumexp(bq, aq, smem)
        ll = bm + math.log(am)
        out_ll[w, i] = ll
        out_lmem[w, i] = bq + math.log(aq) - ll


@njit(cache=True)
def _stream_logsumexp(b, a, v):
    """Add ``exp(v)`` to a running sum held as ``exp(b) * a``; the new ``(b, a)``."""
    if v > b:
        return v, (a * math.exp(b - v) + 1.0 if b > -np.inf else 1.0)
    return b, a + math.exp(v - b)


@njit(cache=True)
def importance_terms_serial(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem):
    """Importance-sum terms of every walker and module on one thread.

    ``x`` (M, D): the draws of all modules, module i's at rows
    ``start[i]:start[i + 1]`` with log weights ``lw0`` (self-normalised per
    module).  Writes ``log L`` and ``log P(member)`` into ``out_ll, out_lmem`` (W, N).
    """
    _importance_chunk(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, 0, out_ll.size)


@njit(cache=True, parallel=True)
def importance_terms_parallel(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, n_chunks):
    """:func:`importance_terms_serial` in ``n_chunks`` parallel chunks."""
    T = out_ll.size
    for c in prange(n_chunks):
        _importance_chunk(
            x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, c * T // n_chunks, (c + 1) * T // n_chunks
        )


# --------------------------------------------------------------------------- the sampler's prior


@njit(cache=True)
def hyper_prep(u, mbar, cbar, sqrt_n, mu_mean, mu_sd, lt_mean, lt_sd, a, b):
    """Sampler coordinates -> population parameters and log prior + Jacobian.

    Same density as :meth:`.model.Population.log_prior` plus the log Jacobian
    of :class:`.hyper.HyperPosterior`'s reparameterisation; -inf outside the
    box (every hyperparameter within :data:`.model.BOX_SDS` prior sds): far
    outside it the closed-form pattern ratios would lose all precision.

    Returns
    -------
    mu, tau : ndarray (W, D)
    logeps, log1m, lp : ndarray (W,)
    """
    W = u.shape[0]
    D = mbar.shape[0]
    mu = np.empty((W, D))
    tau = np.empty((W, D))
    logeps = np.empty(W)
    log1m = np.empty(W)
    lp = np.empty(W)
    for w in range(W):
        lf = u[w, 2 * D]
        v = a * _log_expit(lf) + b * _log_expit(-lf)
        bad = not (abs(lf) <= LOGIT_F_MAX)
        for j in range(D):
            lt = u[w, D + j]
            zt = (lt - lt_mean[j]) / lt_sd[j]
            if not (abs(zt) <= BOX_SDS):
                bad = True
                break
            t = math.exp(lt)
            sc = math.sqrt(t * t + cbar[j]) / sqrt_n
            mu[w, j] = mbar[j] + sc * u[w, j]
            tau[w, j] = t
            zm = (mu[w, j] - mu_mean[j]) / mu_sd[j]
            if not (abs(zm) <= BOX_SDS):
                bad = True
                break
            v += -0.5 * zm * zm - 0.5 * zt * zt + math.log(sc)
        if bad or not math.isfinite(v):
            lp[w] = -np.inf
            for j in range(D):
                mu[w, j] = mu_mean[j]
                tau[w, j] = math.exp(lt_mean[j])
            logeps[w] = -1.0
            log1m[w] = -1.0
            continue
        lp[w] = v
        log1m[w] = _log_expit(-lf) / D  # log(1 - eps) with (1 - eps)^D = 1 - f
        logeps[w] = math.log(-math.expm1(log1m[w]))
    return mu, tau, logeps, log1m, lp
