"""Which effect: a cheap linear-Gaussian screen of the catalogue on held-out data.

Around the calibrated model's mean draw, the held-out run's prediction moves
linearly with

- the base parameters, within their posterior (``J_b``: one column per
  principal direction of the posterior, one sd long), and the run's unknown
  step phase (one column, its uniform prior's sd);
- each effect's parameters, within their prior (one column per parameter, a
  response to ``scale``, the catalogue's prior sd of the effect's size).

With the residual whitened by each channel's residual process
(:class:`~tembayes.predict.anchor.ResidualProcess`), every model is linear
Gaussian: ``w ~ N(0, I + A A^T)`` with ``A`` its columns, and its log
evidence costs a small determinant (Woodbury).  An effect's screen score is
its log Bayes factor against the base model: how much better the effect's
sensitivity pattern explains the residual than the base parameters can.
It also gives the effect's size (posterior mean and sd in the linear model)
and the residual the fit leaves.

This ranks candidates for the recalibration; it is not the final word: an
effect that the base parameters absorb on recalibration, or whose response is
far from linear over its prior, is judged there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tembayes.physics import effects as E
from tembayes.predict.anchor import from_coords, to_coords


@dataclass(frozen=True)
class ScreenResult:
    """Result of :func:`screen_effects`.

    Attributes
    ----------
    ranking : list of dict
        Per effect, best first: ``{"effect", "log_bayes_factor", "size": {param: (mean, sd)},
        "rmse_before", "rmse_after"}`` (RMSE over the temperature channels
        of the grid samples, K, before and after the linear fit with the
        effect; the base-only fit is ``base_rmse``).
    base_log_evidence : float
    base_rmse : float
        RMSE over T1..T4 after the base-only linear fit [K].
    raw_rmse : float
        RMSE over T1..T4 of the mean draw's prediction [K].
    """

    ranking: list
    base_log_evidence: float
    base_rmse: float
    raw_rmse: float


def _log_evidence(w, A):
    """log N(w | 0, I + A A^T) and the posterior mean of the column weights."""
    k = A.shape[1]
    G = np.eye(k) + A.T @ A
    L = np.linalg.cholesky(G)
    b = np.linalg.solve(L, A.T @ w)
    quad = w @ w - b @ b
    logdet = 2.0 * np.sum(np.log(np.diag(L)))
    coef = np.linalg.solve(L.T, b)
    cov = np.linalg.inv(G)
    return -0.5 * (quad + logdet + len(w) * np.log(2 * np.pi)), coef, cov


def screen_effects(model, params, shift_sd, processes, *, names=None, exclude=()):
    """Screen the effect catalogue on a held-out run.

    Parameters
    ----------
    model : RunModel
        The held-out run.
    params : dict
        ``name -> (M,)`` the calibrated module's draws (SI).
    shift_sd : float
        Sd of the run's step shift [s] (uniform over +-bound: bound / sqrt 3).
    processes : dict
        Channel -> ResidualProcess (``T1_C``.. ``voltage_V``).
    names : sequence of str, optional
        Effects to screen (default the whole catalogue).
    exclude : sequence of str
        Effects withheld from the diagnosis.

    Returns
    -------
    ScreenResult
    """
    from tembayes.predict.runmodel import CHANNELS

    names = [n for n in (names or list(E.CATALOGUE)) if n not in set(exclude)]
    keys = [k for k in params if np.ptp(np.asarray(params[k], float)) > 0]
    fixed = {k: float(np.asarray(params[k], float)[0]) for k in params if k not in keys}
    Z = to_coords(params, keys)
    mu = Z.mean(axis=0)
    S = np.cov(Z, rowvar=False)
    evals, evecs = np.linalg.eigh(S)
    keep = evals > 1e-12 * evals.max()
    dirs = evecs[:, keep] * np.sqrt(evals[keep])  # one posterior sd along each principal direction
    base = {**fixed, **{k: float(v[0]) for k, v in from_coords(mu[None], keys).items()}}
    rows = [dict(base)]
    for j in range(dirs.shape[1]):
        rows.append({**fixed, **{k: float(v[0]) for k, v in from_coords((mu + dirs[:, j])[None], keys).items()}})
    effect_cols = []
    for en in names:
        e = E.CATALOGUE[en]
        for p in e.parameters:
            rows.append({**base, p.name: p.scale})
            effect_cols.append((en, p.name, p.scale))
    batch = {k: np.array([r.get(k, 0.0) for r in rows]) for k in set().union(*rows)}
    shifts = np.zeros(len(rows))
    sens, volt = model.simulate(batch, shifts, at="grid")
    sh_s, sh_v = model.simulate({k: v[:1] for k, v in batch.items()}, np.array([shift_sd]), at="grid")
    t = model.time[model.grid_samples]
    exp = model.exp
    idx = model.grid_samples
    y = np.vstack([np.asarray(exp.sensors, float)[:, idx], np.asarray(exp.voltage, float)[idx][None]])
    F = np.concatenate([sens, volt[:, None]], axis=1)  # (rows, 5, n)
    Fs = np.concatenate([sh_s, sh_v[:, None]], axis=1)[0]
    f0 = F[0]

    def whiten(x):
        return np.concatenate([processes[ch].whiten(t, x[..., c, :]) for c, ch in enumerate(CHANNELS)], axis=-1)

    w = whiten(y - f0)
    nb = dirs.shape[1]
    Ab = whiten(F[1:1 + nb] - f0[None]).T
    Ash = whiten((Fs - f0)[None]).T
    A0 = np.hstack([Ab, Ash])
    base_le, coef0, _ = _log_evidence(w, A0)

    base_cols = np.concatenate([F[1:1 + nb] - f0[None], (Fs - f0)[None]], axis=0)

    def rmse_after(cols, coef):
        """RMSE over T1..T4 [K] of the residual left by the linear fit with these columns."""
        r = y - f0 - np.tensordot(coef, cols, axes=1)
        return float(np.sqrt(np.mean(r[:4] ** 2)))

    raw_rmse = float(np.sqrt(np.mean((y - f0)[:4] ** 2)))
    base_rmse = rmse_after(base_cols, coef0)
    ranking = []
    for en in names:
        cols = [i for i, c in enumerate(effect_cols) if c[0] == en]
        D = np.stack([F[1 + nb + i] - f0 for i in cols])
        A = np.hstack([A0, whiten(D).T])
        le, coef, cov = _log_evidence(w, A)
        size = {}
        for k, i in enumerate(cols):
            _, pname, scale = effect_cols[i]
            size[pname] = (float(coef[A0.shape[1] + k] * scale), float(np.sqrt(cov[A0.shape[1] + k, A0.shape[1] + k])
                                                                     * scale))
        ranking.append({"effect": en, "log_bayes_factor": float(le - base_le), "size": size,
                        "rmse_before": base_rmse, "rmse_after": rmse_after(np.concatenate([base_cols, D]), coef)})
    ranking.sort(key=lambda r: -r["log_bayes_factor"])
    return ScreenResult(ranking=ranking, base_log_evidence=float(base_le), base_rmse=base_rmse, raw_rmse=raw_rmse)
