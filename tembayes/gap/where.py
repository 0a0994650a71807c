"""Where the model and the measurements part: the gap map.

From a posterior-predictive of held-out data (a validation run predicted
with ``keep_draws=True``) every sample gets a standardised residual

    z = (y - mean) / sd,   sd^2 = var over draws + mean noise variance,

and every cell (channel x operating regime) the statistic ``T = mean(z^2)``
over its samples: 1 when the measurement scatters inside the band as the
predictive says, larger when it falls outside.  ``score = sqrt(T)``.

The significance is a posterior-predictive check: the same statistic on
replicated data -- each draw's noise-free prediction plus a draw of its
residual process (Ornstein-Uhlenbeck, sampled exactly at the run's uneven
times) -- so parameter uncertainty (a draw's error is smooth and run-long)
and autocorrelated noise are both in the reference distribution.  With a few
hundred replicates a tail probability below 1/M is out of reach, so ``p`` is
read from a scaled chi-square fitted to the replicates' ``T`` by its mean and
variance (``T`` is a mean of squared Gaussians; exact when one run-long
direction dominates and when the noise does); ``p_empirical`` is the plain
count.

Regimes (a sample can be in several families):

- ``Tavg``: bands of T-bar ~ the face sensors' measured mean, 10 K wide;
- ``mode``: heating (I < 0, the bottom block heated), cooling (I > 0), idle;
- ``current``: |I| small / medium / large (thirds of the run's largest |I|);
- ``after_step``: transient (< 120 s after a step), settling (120-600 s),
  steady (> 600 s).

The identification run gets a map of its own (:func:`identification_map`):
each step window predicted from the others by a refit of the base model
(held-out blocks of time), whitened, so that its significance needs no
replicates.

Plus the classic residual tests on the residual sampled every 30 s:
whiteness (Ljung-Box Q over 10 lags) and the largest cross-correlation with
the current over lags 0-10 (the input), each with its replicate p-value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from tembayes.constants import KELVIN

#: Width of the T-bar bands [K].
TAVG_BAND_K = 10.0
#: Transient / settling / steady boundaries after a step [s].
AFTER_STEP_S = (120.0, 600.0)
#: Spacing of the classic residual tests [s].
TEST_SPACING_S = 30.0
#: Lags of the classic tests (at TEST_SPACING_S).
TEST_LAGS = 10
#: Fewest samples of a cell.
MIN_SAMPLES = 60


def regimes(pred):
    """``(family, label, mask)`` of every operating regime of a prediction's run."""
    out = []
    tc = pred.tavg - KELVIN
    lo = np.floor(tc.min() / TAVG_BAND_K) * TAVG_BAND_K
    for a in np.arange(lo, tc.max(), TAVG_BAND_K):
        out.append(("Tavg", f"T_avg {a:.0f}-{a + TAVG_BAND_K:.0f} C", (tc >= a) & (tc < a + TAVG_BAND_K)))
    i = pred.current
    imax = float(np.max(np.abs(i))) or 1.0
    idle = np.abs(i) < 0.05 * imax
    out += [
        ("mode", "heating (I < 0)", (i < 0) & ~idle),
        ("mode", "cooling (I > 0)", (i > 0) & ~idle),
        ("mode", "idle", idle),
    ]
    a = np.abs(i) / imax
    out += [
        ("current", "|I| small", a < 1 / 3),
        ("current", "|I| medium", (a >= 1 / 3) & (a < 2 / 3)),
        ("current", "|I| large", a >= 2 / 3),
    ]
    if pred.since_step is not None:
        s = pred.since_step
        t1, t2 = AFTER_STEP_S
        out += [
            ("after_step", f"transient (< {t1:.0f} s after a step)", s < t1),
            ("after_step", f"settling ({t1:.0f}-{t2:.0f} s)", (s >= t1) & (s < t2)),
            ("after_step", f"steady (> {t2:.0f} s)", s >= t2),
        ]
    return [(f, lab, m) for f, lab, m in out if m.sum() >= MIN_SAMPLES]


def ou_paths(rng, t, sd, tau):
    """Ornstein-Uhlenbeck paths at times ``t`` ``(n,)``, one per row of ``sd``/``tau`` ``(M,)``."""
    sd = np.asarray(sd, float)[:, None]
    tau = np.maximum(np.asarray(tau, float), 1e-9)[:, None]
    phi = np.exp(-np.diff(t)[None, :] / tau)
    e = rng.standard_normal((len(sd), len(t)))
    x = np.empty_like(e)
    x[:, 0] = sd[:, 0] * e[:, 0]
    q = sd * np.sqrt(1.0 - phi * phi)
    for k in range(1, len(t)):
        x[:, k] = phi[:, k - 1] * x[:, k - 1] + q[:, k - 1] * e[:, k]
    return x


def _tail_p(t_obs, t_rep):
    """P(T >= t_obs) under a scaled chi-square fitted to the replicates by their first two moments.

    Satterthwaite's fit is exact for one dominant Gaussian direction (a
    run-long parameter error, chi-square 1) and for many independent ones
    (white noise), and it reaches past 1/M.
    """
    m, v = float(np.mean(t_rep)), float(np.var(t_rep, ddof=1))
    if not (np.isfinite(v) and v > 0 and m > 0):
        return float(t_obs <= m)
    a, nu = v / (2.0 * m), 2.0 * m * m / v
    return float(stats.chi2.sf(t_obs / a, nu))


def _ljung_box(r, lags):
    r = r - r.mean(axis=-1, keepdims=True)
    d = np.sum(r * r, axis=-1)
    n = r.shape[-1]
    q = np.zeros(r.shape[:-1])
    for k in range(1, lags + 1):
        rho = np.sum(r[..., k:] * r[..., :-k], axis=-1) / d
        q += rho * rho / (n - k)
    return n * (n + 2) * q


def _xcorr_max(r, u, lags):
    u = (u - u.mean()) / (u.std() or 1.0)
    r = r - r.mean(axis=-1, keepdims=True)
    sr = r.std(axis=-1)
    sr = np.where(sr > 0, sr, 1.0)
    best = np.zeros(r.shape[:-1])
    n = r.shape[-1]
    for k in range(0, lags + 1):
        c = np.sum(r[..., k:] * u[: n - k], axis=-1) / ((n - k) * sr)
        best = np.maximum(best, np.abs(c))
    return best


@dataclass(frozen=True)
class GapMap:
    """Result of :func:`gap_map`.

    Attributes
    ----------
    cells : list of dict
        ``{"channel", "family", "regime", "n", "score", "p", "p_empirical",
        "outside90"}`` per channel and regime (``score`` = RMS standardised
        residual, 1 = as the band says; ``outside90`` = fraction of samples
        outside the 90 % band).
    channels : dict
        Channel -> the same for the whole run, plus ``ljung_box`` and
        ``xcorr_current`` (``{"stat", "p"}``).
    n_replicates : int
    source : str
    """

    cells: list
    channels: dict
    n_replicates: int
    source: str

    def significant(self, alpha=0.05):
        """Cells whose ``p`` is below ``alpha`` / number of cells (Bonferroni), worst score first."""
        k = max(len(self.cells), 1)
        out = [c for c in self.cells if c["p"] < alpha / k and c["score"] > 1.0]
        return sorted(out, key=lambda c: -c["score"])


def gap_map(pred, rng):
    """The gap map of a :class:`~tembayes.predict.predictive.Prediction` made with ``keep_draws=True``.

    Parameters
    ----------
    pred : Prediction
    rng : numpy.random.Generator
        Draws the replicated noise.

    Returns
    -------
    GapMap
    """
    if pred.deviations is None or pred.noise_sd is None:
        raise ValueError("the prediction has no draws: make it with simulate_predictive(..., keep_draws=True)")
    dev = pred.deviations
    M, nc, n = dev.shape
    tau = pred.noise_tau if pred.noise_tau is not None else np.zeros_like(pred.noise_sd)
    regs = regimes(pred)
    t = pred.time
    # the classic tests on a 30 s grid
    grid = np.searchsorted(t, np.arange(t[0], t[-1], TEST_SPACING_S))
    cells, chans = [], {}
    lo90, hi90 = pred.bands[90]
    for c, ch in enumerate(pred.channels):
        var = dev[:, c].astype(float).var(axis=0) + np.mean(pred.noise_sd[:, c] ** 2)
        sd = np.sqrt(var)
        r_obs = pred.measured[c] - pred.mean[c]
        z_obs = r_obs / sd
        r_rep = dev[:, c].astype(float) + ou_paths(rng, t, pred.noise_sd[:, c], tau[:, c])
        z_rep = r_rep / sd[None]
        outside = (pred.measured[c] < lo90[c]) | (pred.measured[c] > hi90[c])

        def cell(mask, z_obs=z_obs, z_rep=z_rep, outside=outside):
            t_obs = float(np.mean(z_obs[mask] ** 2))
            t_rep = np.mean(z_rep[:, mask] ** 2, axis=1)
            return {
                "n": int(mask.sum()),
                "score": float(np.sqrt(t_obs)),
                "p": _tail_p(t_obs, t_rep),
                "p_empirical": float((1 + np.sum(t_rep >= t_obs)) / (M + 1)),
                "outside90": float(np.mean(outside[mask])),
            }

        whole = cell(np.ones(n, bool))
        lb_obs = _ljung_box(r_obs[grid], TEST_LAGS)
        lb_rep = _ljung_box(r_rep[:, grid], TEST_LAGS)
        xc_obs = _xcorr_max(r_obs[grid], pred.current[grid], TEST_LAGS)
        xc_rep = _xcorr_max(r_rep[:, grid], pred.current[grid], TEST_LAGS)
        whole["ljung_box"] = {"stat": float(lb_obs), "p": _tail_p(lb_obs, lb_rep)}
        whole["xcorr_current"] = {"stat": float(xc_obs), "p": _tail_p(xc_obs, xc_rep)}
        chans[ch] = whole
        for fam, lab, mask in regs:
            cells.append({"channel": ch, "family": fam, "regime": lab, **cell(mask)})
    return GapMap(cells=cells, channels=chans, n_replicates=M, source=pred.source)


#: Phases after a step of the identification map [s]: the voltage jump and the
#: plates (R), the blocks' response, the steady state (S and K).
ID_PHASES_S = (20.0, 120.0)
#: Fewest samples of an identification-map cell (a step window keeps ~50).
ID_MIN_SAMPLES = 20


def identification_map(refit):
    """The gap map of an identification run's held-out step windows.

    Each step window of the identification run, predicted from the others
    by a refit of the base model (:class:`~tembayes.gap.which.Refit`:
    leave-one-window-out, its residuals whitened by their predictive
    covariance, so N(0, 1) under the model).  Cells: every window, the phases
    after a step (:data:`ID_PHASES_S`) and 10 K bands of T-bar, per channel of
    the step likelihood (voltage, sensor dT, sensor mean).  ``score`` is the
    RMS whitened residual and ``p`` its chi-square tail (no replicates
    needed: the residuals are white by construction).

    Returns
    -------
    GapMap
    """
    from tembayes.calibrate.stepdata import CHANNELS as STEP_CHANNELS

    w = refit.windows
    z = np.asarray(refit.cv_z, float)
    step, since, tc = w["step"], np.asarray(w["since"], float), np.asarray(w["tmean_C"], float)
    levels, st = w["levels"], w["step_time"]
    regs = []
    for k in range(len(st)):
        m = step == k
        regs.append(
            (
                "window",
                f"step {k + 1} at {st[k]:.0f} s ({levels[k]:+.2f} -> {levels[k + 1]:+.2f} A, "
                f"T_avg {np.mean(tc[m]):.0f} C)",
                m,
            )
        )
    t1, t2 = ID_PHASES_S
    regs += [
        ("after_step", f"transient (< {t1:.0f} s after a step)", since < t1),
        ("after_step", f"settling ({t1:.0f}-{t2:.0f} s)", (since >= t1) & (since < t2)),
        ("after_step", f"steady (> {t2:.0f} s)", since >= t2),
    ]
    lo = np.floor(tc.min() / TAVG_BAND_K) * TAVG_BAND_K
    for a in np.arange(lo, tc.max(), TAVG_BAND_K):
        regs.append(("Tavg", f"T_avg {a:.0f}-{a + TAVG_BAND_K:.0f} C", (tc >= a) & (tc < a + TAVG_BAND_K)))
    regs = [r for r in regs if r[2].sum() >= ID_MIN_SAMPLES]

    def cell(zc, mask):
        t = float(np.sum(zc[mask] ** 2))
        n = int(mask.sum())
        return {
            "n": n,
            "score": float(np.sqrt(t / n)),
            "p": float(stats.chi2.sf(t, n)),
            "outside90": float(np.mean(np.abs(zc[mask]) > 1.645)),
        }

    cells, chans = [], {}
    for c, ch in enumerate(STEP_CHANNELS):
        chans[ch] = cell(z[c], np.ones(z.shape[1], bool))
        for fam, lab, mask in regs:
            cells.append({"channel": ch, "family": fam, "regime": lab, **cell(z[c], mask)})
    return GapMap(
        cells=cells,
        channels=chans,
        n_replicates=0,
        source=f"{w['source']} (each step window predicted from the others)",
    )
