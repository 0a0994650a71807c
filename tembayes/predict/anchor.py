"""Anchor the rig on the identification run's absolute temperatures.

The step likelihood looks at the voltage and at the face sensors' difference
and mean with one free offset per step window: it learns R, S and K from how
the run *moves*, and leaves what sets the rig's temperature *levels* -- on the
reference rig the water cooler's conductance, the enclosure leaks, the tabs --
close to their priors (``g_cooler`` is known to +-10 %: +-0.15 K on T1 at
15 W).  A prediction of every sensor needs those levels, so they are calibrated
here, from the same run's sensors at every grid point of
:class:`~tembayes.predict.runmodel.RunModel`.

The update is Gaussian in the step posterior's whitened coordinates ``u``
(``z = mu + L u``, ``z`` the log of every positive parameter, the slopes as
they are, ``L L^T`` the step posterior's covariance):

    minimise  |u|^2 / 2 + |W (y - f(mu + L u))|^2 / 2

by Gauss-Newton (batched finite-difference Jacobians, ``u`` steps of one
posterior sd), where ``W`` whitens each channel's residual as an
Ornstein-Uhlenbeck process (scale and time constant fitted to the residuals
of a first pass with the sensors' white noise): residuals of a model on a real
rig are smooth and autocorrelated, and weighting them as white would make the
update overconfident.  The posterior in ``u`` is ``N(u*, (I + J^T J)^-1)``;
every step-posterior draw is carried there by the affine map that takes the
step posterior's whitened draws to it, so the non-Gaussian shape of the draws
survives.  The four sensors' levels are data the step likelihood did not use
(their window offsets were integrated out), so the update counts no data
twice except the small level information that survives those offsets.

The fitted residual processes are the predictive's noise: the measurement
noise plus whatever model discrepancy the identification run shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from tembayes.calibrate.priors import ParameterPrior, expit, logit
from tembayes.common.ou import fit_ou, innovations
from tembayes.common.seeds import stream
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data.quality import noise_estimate
from tembayes.errors import ModelError
from tembayes.physics.effects import EFFECT_PARAMETERS
from tembayes.physics.rigfile import CERAMIC
from tembayes.predict.runmodel import VOLTAGE

#: Parameters sampled on their natural scale (can be negative); every other
#: simulation parameter is positive and handled in log.
LINEAR = ("R1_ohm_per_K", "S1_V_per_K2", *EFFECT_PARAMETERS)

#: Finite-difference step in whitened coordinates (posterior sds).
FD_STEP = 1.0


def _coordinate(k, x, shares):
    x = np.asarray(x, float)
    if k in LINEAR:
        return x
    return logit(x) if k in shares else np.log(x)


def _value(k, z, shares):
    if k in LINEAR:
        return z
    return expit(z) if k in shares else np.exp(z)


def to_coords(draws, names, shares=frozenset()):
    """``(M, p)`` coordinates (the log of positive parameters, the logit of ``shares``) of ``name -> (M,)`` draws."""
    return np.column_stack([_coordinate(k, draws[k], shares) for k in names])


def from_coords(Z, names, shares=frozenset()):
    """``name -> (M,)`` parameter values of coordinates ``Z`` ``(M, p)``."""
    Z = np.atleast_2d(Z)
    return {k: _value(k, Z[:, j], shares) for j, k in enumerate(names)}


@dataclass(frozen=True)
class ResidualProcess:
    """An Ornstein-Uhlenbeck model of one channel's residual.

    Attributes
    ----------
    sd : float
        Stationary standard deviation (SI: K or V).
    tau_s : float
        Correlation time [s].
    rmse : float
        RMS of the residual it was fitted to.
    """

    sd: float
    tau_s: float
    rmse: float

    def whiten(self, t, r):
        """Innovations of residuals ``r`` at times ``t`` (:func:`tembayes.common.ou.innovations`)."""
        return innovations(t, r, self.sd, self.tau_s)

    def to_dict(self):
        """``{"sd", "tau_s", "rmse"}`` (``metrics.json``'s ``anchor.residual``)."""
        return {"sd": self.sd, "tau_s": self.tau_s, "rmse": self.rmse}


def fit_residual_process(t, r, floor):
    """Maximum-likelihood :class:`ResidualProcess` of residuals ``r`` at times ``t``.

    The whole residual, white noise included, is one OU process
    (:func:`tembayes.common.ou.fit_ou` without white noise): it is the
    predictive's noise, and the whitening weights of the anchoring.
    ``floor`` is the least sd (the channel's measurement noise).
    """
    r = np.asarray(r, float)
    fit = fit_ou(t, r)
    return ResidualProcess(float(max(fit.sd, floor)), fit.tau_s, float(np.sqrt(np.mean(r * r))))


#: A rig parameter is *unpinned* by the step likelihood when its step
#: posterior keeps more than this fraction of its prior sd.
UNPINNED_FRACTION = 0.5


def unpinned(draws, priors, rig, fraction=UNPINNED_FRACTION):
    """Rig parameters the step likelihood leaves near their prior.

    Parameters
    ----------
    draws : dict
        ``name -> (M,)`` step-posterior draws (SI).
    priors : dict
        ``name -> {"kind", "center", "scale"}`` (the run's recorded priors).
    rig : RigDescription
    fraction : float
        Posterior sd over prior sd above which a parameter counts as unpinned.

    Returns
    -------
    tuple of str
    """
    out = []
    for k in rig.parameter_names:
        if k not in draws or k not in priors or priors[k]["kind"] == "uniform":
            continue
        if np.std(ParameterPrior(k, **priors[k]).z(draws[k])) > fraction:
            out.append(k)
    return tuple(out)


def held_draws(rig, draws, priors, label):
    """Draws of the rig parameters the calibration held, for the anchoring to update.

    A parameter the rig file marks ``held`` is held at its nominal value in the
    step likelihood (with ``--discrepancy robust`` its uncertainty is carried
    over to the laws), yet the block sensors' levels and transients tell it.
    A sensor's depth below its block's face: in the bottom block, which holds
    no steady heat flow, one a quarter of a millimetre off its nominal depth
    reads ~20 mK off while the block heats at 0.15 K/s and nothing at steady
    state, so at its nominal value every step's transient shows as a gap; in
    the top block, which carries the module's heat to the cooler, it also reads
    a steady offset (~0.15 K at 15 W), where the depth shares the data with
    ``g_cooler``.  A module face's leak to the room sets how the load block's
    level follows the room against the cold face's.  Their draws join the
    anchoring: the carry-over's own draws when the run kept them (each draw's
    value is the one its laws were moved for), otherwise (or where the
    carry-over could not move it, its draws all at the held value) independent
    draws from the carry-over's prior (log-normal about the nominal value, or
    logit-normal for a share, the sd of a uniform draw over its documented
    range), which the cut update conditions on the laws.  Left with the other
    parameters (simulated as they are) is the module's own held parameter
    (``g_ceramic``): it acts between the junctions and the faces, where the
    block sensors cannot separate it from the pastes.

    Held parameters must be updated, not simulated as given: a given
    parameter's spread is carried into the updated ones by a correction
    linear in its deviation, and a held parameter's spread (its whole range)
    is too wide for that -- a face leak spread over 0.001-0.01 W/K moved the
    updated heat capacities by orders of magnitude.

    Parameters
    ----------
    rig : RigDescription
        The calibration rig (its parameters' ``held`` flags, its sensors' ``depths``).
    draws : dict
        ``name -> (M,)`` the run's draws: sampled parameters (those with a
        prior) and carried-over held ones.
    priors : dict
        The run's priors (a held parameter with one was sampled and is left out).
    label : str
        The module's id: seeds the independent draws (:func:`tembayes.common.seeds.stream`).

    Returns
    -------
    dict
        ``name -> (M,)`` value (SI) of every held rig parameter and sensor depth with a range.
    """
    n = len(next(iter(draws.values())))
    depths = {d.parameter for d in rig.depths.values()}  # held, or fixed for a range too narrow to sample
    out = {}
    for q in rig.parameters:
        if not (q.held or q.name in depths) or q.name == CERAMIC.name or q.name in priors or q.high <= q.low:
            continue
        kept = np.asarray(draws.get(q.name, ()), float)
        if kept.size and np.ptp(kept) > 0:
            out[q.name] = kept
        else:  # not kept, or kept at its held value because the carry-over could not move it
            out[q.name] = q.moved(q.nominal, q.spread_sd * stream(0, "held", label, q.name).standard_normal(n))
    return out


@dataclass(frozen=True)
class Anchored:
    """Result of :func:`anchor_rig`.

    Attributes
    ----------
    names : tuple of str
        The updated (unpinned) parameters.
    draws : dict
        ``name -> (M,)`` the updated draws (SI), plus ``step_shift_s``.
    prior_sd, posterior_sd : dict
        Sd of each updated parameter's coordinate in the step posterior and
        after the update (log for positive parameters).
    residual : dict
        Channel (the rig's sensor columns, ``voltage_V``) -> :class:`ResidualProcess` at the
        updated mode.
    shift : float
        Step shift used for the identification run [s].
    iterations : int
        Model evaluations of the optimiser.
    """

    names: tuple
    draws: dict
    prior_sd: dict
    posterior_sd: dict
    residual: dict
    shift: float
    iterations: int

    def to_dict(self):
        """What the anchoring did, as plain data (``metrics.json``'s ``anchor``)."""
        return {
            "prior_sd": self.prior_sd,
            "posterior_sd": self.posterior_sd,
            "residual": {k: v.to_dict() for k, v in self.residual.items()},
            "shift_s": self.shift,
            "iterations": self.iterations,
        }


def anchor_rig(model, draws, names, *, shift=None, fixed=None):
    """Condition the unpinned rig parameters on the identification run's block sensors.

    A *cut* update (Plummer 2015): the laws, K and the pinned rig parameters
    (``given``: every other simulation parameter in ``draws``) keep their step
    posterior; the parameters ``names`` are updated given them.  Per draw
    ``i``, their step posterior conditional on the draw's ``given`` values,
    ``N(mu_c + B (g_i - g_mean), Lc Lc^T)`` from the draws' linear regression,
    is the prior; with the updated parameters ``mu_c + B (g_i - g_mean) + Lc u``
    the update is linearised around the mean draw:
    ``u_i = u* - P J_u^T (J_g + J_u Lc^-1 B) (g_i - g_mean) + chol(P) xi_i``,
    with ``xi_i`` the draw's own whitened residual (its shape survives) and
    ``P = (I + J_u^T J_u)^-1``.

    Parameters
    ----------
    model : RunModel
        The identification run.
    draws : dict
        ``name -> (M,)`` step-posterior draws (SI) of the simulation
        parameters (and optionally ``step_shift_s``).
    names : sequence of str
        The parameters to update (may be empty: then only the residual
        processes are fitted).
    shift : float, optional
        Step shift of the run [s]; default the draws' mean ``step_shift_s``.
    fixed : dict, optional
        Parameters held at a value in every draw (e.g. zero slopes).

    Returns
    -------
    Anchored
    """
    known = set(MODULE_PARAMETERS) | set(model.rig.parameter_names) | set(EFFECT_PARAMETERS)
    names = tuple(names)
    fixed = dict(fixed or {})
    given = tuple(k for k in draws if k in known and k not in names and k not in fixed)
    if shift is None:
        shift = float(np.mean(draws["step_shift_s"])) if "step_shift_s" in draws else 0.0
    shift = float(np.clip(shift, -model.shift_bound, model.shift_bound)) if model.shift_bound > 0 else 0.0
    shares = frozenset(q.name for q in model.rig.parameters if q.is_share)
    Zg = to_coords(draws, given, shares)
    M = Zg.shape[0]
    mg = Zg.mean(axis=0)
    p = len(names)
    exp = model.exp
    idx = model.grid_samples
    t = model.time[idx]
    y = model.measured[:-1, idx]
    v = model.measured[-1, idx]
    ns = len(model.sensor_channels)
    floor = np.array([noise_estimate(x) for x in model.measured[:-1]])
    floor = np.where(np.isfinite(floor) & (floor > 0), floor, 1e-3)
    calls = {"n": 0}

    def simulate(Zu, Zgiven):
        n = len(Zu)
        params = {
            **from_coords(np.broadcast_to(Zgiven, (n, len(given))), given, shares),
            **{k: np.full(n, val) for k, val in fixed.items()},
        }
        if p:
            params.update(from_coords(Zu, names, shares))
        calls["n"] += 1
        return model.simulate(params, np.full(n, shift), at="grid")

    if p:
        Zu = to_coords(draws, names, shares)
        mu = Zu.mean(axis=0)
        # the updated parameters' step posterior given the others: a linear regression on the draws
        Dg, Du = Zg - mg, Zu - mu
        B = np.linalg.lstsq(Dg, Du, rcond=None)[0].T if len(given) else np.zeros((p, 0))
        R = Du - Dg @ B.T
        Lc = np.linalg.cholesky(np.atleast_2d(np.cov(R, rowvar=False)) + 1e-14 * np.eye(p))
        Xi = np.linalg.solve(Lc, R.T).T

        def make(processes):
            cache = {}

            def fun(u):
                U = np.vstack([u, u[None] + FD_STEP * np.eye(p)])
                sens, _ = simulate(mu[None] + U @ Lc.T, mg)
                W = np.concatenate([processes[c].whiten(t, y[c][None] - sens[:, c]) for c in range(ns)], axis=1)
                cache["u"], cache["J"] = u.copy(), ((W[1:] - W[0][None]) / FD_STEP).T
                return np.concatenate([u, W[0]])

            def jac(u):
                if "u" not in cache or not np.array_equal(cache["u"], u):
                    fun(u)
                return np.vstack([np.eye(p), cache["J"]])

            return fun, jac, cache

        def solve(processes, u0):
            fun, jac, cache = make(processes)
            res = least_squares(fun, u0, jac=jac, method="trf", xtol=1e-6, ftol=1e-9, max_nfev=30)
            if not np.all(np.isfinite(res.x)):
                raise ModelError(f"anchoring the rig on {exp.path} failed: {res.message}")
            jac(res.x)
            return res.x, cache["J"]

        white = {c: ResidualProcess(float(floor[c]), 1e-6, float(floor[c])) for c in range(ns)}
        u1, _ = solve(white, np.zeros(p))
        sens1, _ = simulate(mu[None] + u1[None] @ Lc.T, mg)
        processes = {c: fit_residual_process(t, y[c] - sens1[0, c], floor[c]) for c in range(ns)}
        u_star, Ju = solve(processes, u1)
        zu_star = mu + Lc @ u_star
        # the data's pull on the given parameters, for the per-draw correction
        sg = Zg.std(axis=0)
        sg = np.where(sg > 0, sg, 1e-9)
        Gz = np.vstack([mg, mg[None] + np.diag(sg)])
        sens, _ = simulate(np.broadcast_to(zu_star, (len(Gz), p)), Gz)
        W = np.concatenate([processes[c].whiten(t, y[c][None] - sens[:, c]) for c in range(ns)], axis=1)
        Jg = ((W[1:] - W[0][None]) / sg[:, None]).T
        P = np.linalg.inv(np.eye(p) + Ju.T @ Ju)
        Lp = np.linalg.cholesky(0.5 * (P + P.T))
        # a draw's given parameters move the data directly (Jg) and through the
        # conditional prior mean of the updated ones (B), which u is measured from
        Jeff = Jg + Ju @ np.linalg.solve(Lc, B) if len(given) else Jg
        U = u_star[None] - (Dg @ (P @ Ju.T @ Jeff).T) + Xi @ Lp.T
        Znew = mu[None] + Dg @ B.T + U @ Lc.T
        new = from_coords(Znew, names, shares)
        prior_sd = dict(zip(names, np.sqrt(np.diag(np.atleast_2d(np.cov(Zu, rowvar=False)))).tolist()))
        posterior_sd = dict(zip(names, np.atleast_1d(Znew.std(axis=0)).tolist()))
        mode = (zu_star[None], mg)
    else:
        new, prior_sd, posterior_sd = {}, {}, {}
        mode = (np.zeros((1, 0)), mg)
    new.update({k: np.asarray(draws[k], float) for k in given})
    new.update({k: np.full(M, float(val)) for k, val in fixed.items()})
    if "step_shift_s" in draws:
        new["step_shift_s"] = np.asarray(draws["step_shift_s"], float)
    # the residual processes at the updated mode, voltage included: the predictive's noise
    sens2, volt2 = simulate(*mode)
    residual = {ch: fit_residual_process(t, y[c] - sens2[0, c], floor[c]) for c, ch in enumerate(model.sensor_channels)}
    vfloor = noise_estimate(model.measured[-1])
    vfloor = float(vfloor) if np.isfinite(vfloor) and vfloor > 0 else 1e-4
    residual[VOLTAGE] = fit_residual_process(t, v - volt2[0], vfloor)
    return Anchored(
        names=names,
        draws=new,
        prior_sd=prior_sd,
        posterior_sd=posterior_sd,
        residual=residual,
        shift=shift,
        iterations=calls["n"],
    )
