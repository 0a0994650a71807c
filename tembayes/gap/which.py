"""Which effect: the catalogue screened by refitting the identification run.

The base model and, one at a time, the base model with each catalogue effect
added are refitted to the module's identification run: the posterior mode of
the calibration's own step-response model and priors
(:func:`~tembayes.calibrate.module.fit_map`: white noise at the measured
level and no window offsets, so that a misfit shows instead of being
absorbed) and its Laplace approximation.  Every refit starts from the same
point -- the base posterior's laws, the rig at its nominal, the effect at
zero -- so the base refit is the fair control of the others: an effect is
credited with what it adds, not with a better start.

An effect the base model cannot absorb leaves the base refit far above the
noise floor (``chi2`` per sample well above 1) and takes the refit with the
true effect down to it; one the base model absorbs in a rig parameter
(a contact resistance in the paste, an ambient leak in the enclosure's)
fits either way and shows as that parameter outside its documented range
(:mod:`~tembayes.gap.conflicts`), back inside with the effect.

Every refit also predicts each step window of the identification run from
the others -- leave-one-window-out cross-validation, exact for the model
linearised at the mode (the hat-matrix identity: window ``k``'s held-out
residual is ``(I - H_kk)^-1 r_k`` with covariance ``(I - H_kk)^-1`` in noise
units, ``H = J (J^T J)^-1 J^T`` over the data and prior rows).  These are
*held-out blocks of time*: the identification run's gap map
(:func:`~tembayes.gap.where.identification_map`) and its share of the
held-out evidence come from them.  On a correctly specified bench module the
held-out windows scatter as the noise says (measured at white noise, before
the noise model below: ``chi2`` 1.01, no window above 1.25 noise sds); a
Thomson heat the linear laws half absorb left windows at 2-2.5 sds.

The held-out residuals are whitened by the noise model of the base
calibration (:class:`WindowNoise`: its noise scale and window offsets, which
carry a sensor's slow noise, each within its adequacy limit), so a window
counts as a gap only beyond what that model allows: a sensor's slow noise,
which the second differences of the measured noise level do not see, would
otherwise read as a misfit.  It is one yardstick for the base and every
candidate of a diagnosis (a candidate's own noise may have absorbed what it
does not explain).  The windows' log densities stay on the white noise at
the measured level, as the Laplace evidence is: the comparison between
effects is on one noise model.  A calibration without noise parameters
leaves the windows at white noise (``window_noise`` None in ``gap.json``).

The screen ranks the effects by their Laplace log evidence on the
identification run against the base refit's; the diagnosis
(:mod:`~tembayes.gap.diagnose`) also predicts the held-out runs from each
refit's Laplace posterior, and recalibrates the strongest candidates with
the sampler.  Measured on bench modules (one 4-hour staircase at 5 Hz): the
refit with the true effect reaches chi2 ~ 1.0 in ~20 model evaluations and
recovers the effect's size to a percent; the wrong ones stall at 3-30x the
floor.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from tembayes.calibrate.stepdata import CHANNELS as STEP_CHANNELS
from tembayes.constants import KELVIN
from tembayes.physics import effects as E

#: Model evaluations (Jacobians not counted) of a refit's mode search.
MAX_NFEV = 60


@dataclass(frozen=True)
class WindowNoise:
    """The noise model a held-out step window is judged by: a calibration's, per channel of the step likelihood.

    Attributes
    ----------
    scale : ndarray, shape (3,)
        Each channel's noise sd over its measured level (``noise_scale_*``).
    offset_sd : ndarray, shape (3,)
        Each channel's window-offset sd (``offset_sd_*``) [V, K, K].
    """

    scale: np.ndarray
    offset_sd: np.ndarray

    @classmethod
    def of_draws(cls, draws):
        """The posterior medians of a calibration's noise parameters; None if the draws have none.

        Parameters
        ----------
        draws : mapping of str to array_like
            A module's posterior draws (SI).
        """
        from tembayes.calibrate.likelihood import NOISE_SCALE, OFFSET_SD

        if not all(q in draws for q in NOISE_SCALE + OFFSET_SD):
            return None
        med = [float(np.median(np.asarray(draws[q], float))) for q in NOISE_SCALE + OFFSET_SD]
        return cls(scale=np.array(med[:3]), offset_sd=np.array(med[3:]))

    def whitened(self, noise):
        """``(scale, offset_sd / noise)`` in units of the measured noise levels ``noise`` (3,), within the limits.

        Within the limits (:data:`~tembayes.calibrate.adequacy.LIMITS`, about twice what a model
        that is right gave on the benches) the noise parameters are noise; beyond them they carry
        a misfit the model absorbed there, which the windows must not be excused.  The scale is
        at least 1: the level the run itself measures is the floor (a correctly specified bench
        module's posterior puts it at 0.97-0.98, which would raise every window's score by 2-3 %).
        """
        from tembayes.calibrate.adequacy import LIMITS

        scale = np.clip(self.scale, 1.0, LIMITS["noise_scale"])
        offset = np.minimum(self.offset_sd / np.asarray(noise, float), LIMITS["window_offsets"])
        return scale, offset


@dataclass(frozen=True)
class Refit:
    """A model refitted on a module's identification run (:func:`refit`).

    Attributes
    ----------
    module_id : str
    effect : str or None
        The catalogue effect added (None: the base model).
    names : tuple of str
        Coordinates (the calibration's parameter space without the noise).
    x : ndarray, shape (p,)
        Posterior mode (coordinates).
    cov : ndarray, shape (p, p)
        Laplace covariance at the mode.
    priors : dict
        ``name -> ParameterPrior.to_dict()``.
    chi2 : dict
        Step-likelihood channel -> mean squared standardised residual at the
        mode (1 at the noise floor).
    n : int
        Residuals (samples x channels).
    data_cost : float
        ``sum(r^2) / 2`` over the standardised residuals [nats].
    log_evidence : float
        Laplace log evidence [nats], up to a constant shared by every refit
        of the same run.
    cv_lpd : ndarray, shape (n_windows,)
        Leave-one-window-out log predictive density of every step window
        [nats, noise units: a constant shared by every refit of the run left out].
    cv_z : ndarray, shape (3, n)
        The windows' held-out residuals, whitened by their predictive
        covariance under ``window_noise`` (N(0, 1) under the model).
    window_noise : dict or None
        The noise model the windows were judged by, in units of the measured
        noise levels: ``{"scale": [3], "offset": [3]}`` (None: white).
    windows : dict
        What the identification map needs of the run: ``step``, ``since``
        (per sample), ``tmean_C`` (measured sensor mean, per sample),
        ``levels``, ``step_time``, ``source``.
    nfev : int
        Model evaluations of the mode search.
    converged : bool
        The mode search stopped on a tolerance, not on :data:`MAX_NFEV`.
    seconds : float
    held : dict or None
        Rig parameters held at a value (SI) instead of refitted: a range check's refit
        (:mod:`~tembayes.gap.conflicts`).
    """

    module_id: str
    effect: str | None
    names: tuple
    x: np.ndarray
    cov: np.ndarray
    priors: dict
    chi2: dict
    n: int
    data_cost: float
    log_evidence: float
    cv_lpd: np.ndarray
    cv_z: np.ndarray
    window_noise: dict | None
    windows: dict
    nfev: int
    converged: bool
    seconds: float
    held: dict | None = None

    @property
    def chi2_total(self):
        """``2 data_cost / n``: 1 at the noise floor."""
        return 2.0 * self.data_cost / self.n

    @property
    def cv_chi2(self):
        """Mean squared whitened held-out residual of the windows: 1 at the noise floor."""
        return float(np.mean(self.cv_z.astype(float) ** 2))

    @property
    def space(self):
        """The refit's :class:`~tembayes.calibrate.parameters.ParameterSpace` (its priors)."""
        from tembayes.calibrate.parameters import ParameterSpace
        from tembayes.calibrate.priors import ParameterPrior

        return ParameterSpace(tuple(ParameterPrior(k, **self.priors[k]) for k in self.names), dict(self.held or {}))

    def mode(self):
        """``name -> value`` (SI) at the mode, the held values with it."""
        return {**(self.held or {}), **{k: float(v[0]) for k, v in self.space.values(self.x[None]).items()}}

    def draws(self, rng, n):
        """``name -> (n,)`` draws (SI) of the Laplace posterior (bounded coordinates clipped), held values included."""
        space = self.space
        X = space.clip(rng.multivariate_normal(self.x, self.cov, size=n, method="eigh"))
        return {**{k: np.full(n, v) for k, v in (self.held or {}).items()}, **space.values(X)}

    def size(self):
        """The effect's parameters at the mode: ``{name: {"mode", "sd", "unit"}}`` (SI); empty for the base."""
        if self.effect is None:
            return {}
        out = {}
        for p in E.get(self.effect).parameters:
            j = self.names.index(p.name)  # effect coordinates are SI (normal or uniform priors)
            out[p.name] = {"mode": float(self.x[j]), "sd": float(np.sqrt(max(self.cov[j, j], 0.0))), "unit": p.unit}
        return out

    def summary(self):
        """A JSON-ready record (``gap.json``'s screen rows)."""
        return {
            "effect": self.effect,
            "log_evidence": self.log_evidence,
            "chi2": self.chi2_total,
            "chi2_channels": self.chi2,
            "cv_chi2": self.cv_chi2,
            "window_noise": self.window_noise,
            "cv_elpd": float(np.sum(self.cv_lpd)),
            "size": self.size(),
            "nfev": self.nfev,
            "converged": self.converged,
            "seconds": self.seconds,
        }


def refit(
    module,
    datasheet,
    effect=None,
    *,
    rig_config=None,
    start=None,
    options=None,
    window_noise=None,
    max_nfev=MAX_NFEV,
    held=None,
):
    """Refit a module's identification run with the base model or one effect added.

    Parameters
    ----------
    module : tembayes.data.Module
    datasheet : tembayes.data.Datasheet
    effect : str, optional
        Catalogue effect added to the base model (None: the base model).
    rig_config : dict, optional
        The batch's ``[rig]`` table.
    start : dict, optional
        ``name -> value`` (SI) where the search starts (e.g. the base
        posterior's laws); default the prior centres, the effects at zero and
        the step shift at the middle of its interval.
    options : CalibrationOptions, optional
        The calibration's resolution (``leg_cells``, ``block_split``).
    window_noise : WindowNoise, optional
        The noise model the held-out windows are judged by (the base
        calibration's); default white noise at the measured level.
    max_nfev : int
    held : dict, optional
        ``name -> value`` (SI): parameters held there instead of refitted.

    Returns
    -------
    Refit
    """
    from tembayes.calibrate.module import laplace_fit

    t0 = time.perf_counter()
    effects = () if effect is None else (E.get(effect).name,)
    fit = laplace_fit(
        module.identification,
        datasheet,
        rig_config=rig_config,
        options=options,
        effects=effects,
        start=start,
        max_nfev=max_nfev,
        held=held,
    )
    data, space, x, cov, J, r = fit.data, fit.space, fit.x, fit.cov, fit.jac, fit.residuals
    data_cost = 0.5 * float(np.sum(r * r))
    _, logdet = np.linalg.slogdet(cov)
    log_evidence = -data_cost + float(space.log_prior(x[None])[0]) + 0.5 * (len(x) * np.log(2 * np.pi) + logdet)
    wn = None if window_noise is None else window_noise.whitened(data.noise)
    cv_lpd, cv_z = window_cv(J[: r.size], r, cov, data.step, wn)
    return Refit(
        module_id=module.id,
        effect=effects[0] if effects else None,
        names=space.names,
        x=x,
        cov=cov,
        priors={p.name: p.to_dict() for p in space.priors},
        chi2={c: float(np.mean(r[k] ** 2)) for k, c in enumerate(STEP_CHANNELS)},
        n=int(r.size),
        data_cost=data_cost,
        log_evidence=float(log_evidence),
        cv_lpd=cv_lpd,
        cv_z=cv_z,
        window_noise=None if wn is None else {"scale": wn[0].tolist(), "offset": wn[1].tolist()},
        windows=step_windows(data),
        nfev=fit.nfev,
        converged=fit.converged,
        seconds=time.perf_counter() - t0,
        held=dict(held) if held else None,
    )


def step_windows(data):
    """What the identification map needs of a run's step data (``Refit.windows``)."""
    return {
        "step": data.step,
        "since": data.since.astype(np.float32),
        "tmean_C": (data.obs[2] - KELVIN).astype(np.float32),
        "levels": data.levels,
        "step_time": data.step_time,
        "source": data.source,
    }


def window_cv(J, r, cov, step, noise=None):
    """Leave-one-window-out predictions of a model linearised at its mode.

    Parameters
    ----------
    J : ndarray, shape (nc * n, p)
        Jacobian of the whitened residuals, channel-major rows (``c * n + i``).
    r : ndarray, shape (nc, n)
        Whitened residuals at the mode.
    cov : ndarray, shape (p, p)
        ``(J_all^T J_all)^-1`` over every row (data and prior).
    step : ndarray of int, shape (n,)
        Window of every sample.
    noise : tuple of ndarray, optional
        ``(scale, offset)``, each (nc,), in units of the whitening: the noise
        model the residuals ``z`` are judged by (:meth:`WindowNoise.whitened`).
        Default white at the whitening's level.

    Returns
    -------
    lpd : ndarray, shape (n_windows,)
        Log predictive density of each window given the others, under white
        noise at the whitening's level [nats].
    z : ndarray, shape (nc, n), float32
        Each window's held-out residual ``e_k = (I - H_kk)^-1 r_k`` whitened
        by its predictive covariance ``C_k = (I - H_kk)^-1 - I + S_k``, ``S_k``
        the noise model's covariance of the window (``scale^2 I + offset^2 1 1^T``
        per channel; ``I`` for white noise, which gives ``z_k = L^-1 r_k``
        with ``I - H_kk = L L^T``): N(0, I) under the model, to first order
        in the offsets.  The parameters' part ``(I - H_kk)^-1 - I`` is the
        white fit's; under window offsets the fit's estimate scatters more
        (a sandwich), which this leaves out: negligible at the out-of-model
        benches' offsets (<= 0.35 noise sds), a mean z^2 of 1.1-1.2 at 1-2.
    """
    nc, n = r.shape
    ns = int(step.max()) + 1
    lpd = np.empty(ns)
    z = np.empty((nc, n), np.float32)
    for k in range(ns):
        idx = np.flatnonzero(step == k)
        rows = (np.arange(nc)[:, None] * n + idx[None]).ravel()
        Jk = J[rows]
        A = np.eye(len(rows)) - Jk @ cov @ Jk.T
        L = np.linalg.cholesky(0.5 * (A + A.T))
        rk = r[:, idx].ravel()
        w = np.linalg.solve(L, rk)  # ||w||^2 = r^T A^-1 r; z = L^T A^-1 r = L^-1 r
        lpd[k] = -0.5 * float(w @ w) + float(np.sum(np.log(np.diag(L)))) - 0.5 * len(rows) * np.log(2 * np.pi)
        if noise is None:
            z[:, idx] = w.reshape(nc, -1)
        else:
            z[:, idx] = _whiten_window(L, w, len(idx), *noise).reshape(nc, -1)
    return lpd, z


def _whiten_window(L, w, m, scale, offset):
    """A window's held-out residual whitened by ``C_k`` (see :func:`window_cv`).

    ``L L^T = I - H_kk`` and ``w = L^-1 r_k`` (the white case's ``z``).  With
    ``C_k = A^-1 + D``, ``D = S_k - I``, the residual ``L^T e_k = w`` has
    covariance ``M = I + L^T D L``, so ``chol(M)^-1 w`` is white; ``D = 0``
    gives ``w`` itself.
    """
    D = np.zeros((len(w), len(w)))
    for c in range(len(scale)):
        sl = slice(c * m, (c + 1) * m)
        D[sl, sl] = (scale[c] ** 2 - 1.0) * np.eye(m) + offset[c] ** 2
    M = np.eye(len(w)) + L.T @ D @ L
    return np.linalg.solve(np.linalg.cholesky(0.5 * (M + M.T)), w)
