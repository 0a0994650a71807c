"""Uncertainty inputs for observer design (``tembayes export``).

Per calibrated module, and for a new module of the batch (the population):

- the posterior mean and covariance of the laws, ``K`` and the rig
  parameters (the rig anchored on the identification run, as ``tembayes
  predict`` does), and a thinned set of posterior draws (for a UKF's sigma
  points or a robust design's scenarios);
- the sensors' measurement-noise covariance (the rig's sensors, V), read off the
  identification run: second differences, robust scale on the diagonal,
  correlations from the samples away from the current steps;
- a process-noise suggestion: the model discrepancy as one Ornstein-Uhlenbeck
  disturbance per output (``d' = -d/tau + w``, ``y = C x + D u + d + v``),
  fitted to the posterior-predictive residuals of the held-out runs when
  the module has any, else to the identification run's (``source`` says
  which); ``q = 2 sd^2 / tau`` is the spectral density of ``w``;
- the rig linearised at the operating points asked for
  (:mod:`tembayes.export.linearise`), with its sensitivities to every
  exported parameter.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tembayes.common.draws import thin
from tembayes.common.ou import fit_ou, spectral_density
from tembayes.constants import KELVIN, MODULE_PARAMETERS
from tembayes.data.quality import noise_estimate
from tembayes.errors import DataError
from tembayes.export.coverage import boundary_warnings, calibrated_range, check_points, default_points
from tembayes.export.linearise import io_names, linearise
from tembayes.predict.predictive import module_draws, predict

#: Draws of the held-out posterior predictive whose residuals give the process noise.
HELDOUT_DRAWS = 100
#: Units of the five module parameters (the rig's come from the rig description).
MODULE_UNITS = {
    "R0_ohm": "ohm",
    "R1_ohm_per_K": "ohm/K",
    "S0_V_per_K": "V/K",
    "S1_V_per_K2": "V/K^2",
    "K_W_per_K": "W/K",
}


@dataclass(frozen=True)
class ModuleExport:
    """The export of one module (or of a new unit of the batch, ``population``); SI.

    Attributes
    ----------
    mean : ndarray, shape (p,)
        Posterior mean over :attr:`ObserverExport.parameters`.
    cov : ndarray, shape (p, p)
        Posterior covariance.
    draws : ndarray, shape (d, p)
        Evenly thinned posterior draws.
    n_posterior : int
        Posterior draws behind ``mean`` and ``cov``.
    measurement_noise_cov : ndarray, shape (nch, nch)
        White sensor noise over the outputs [K^2, K V, V^2].
    process_noise : dict
        One OU disturbance per output (:func:`_ou_noise`), with held-out runs
        also its structure (:func:`disturbance_structure`).
    input_noise : dict
        :func:`input_noise`.
    linear : list of LinearModel
        One per operating point.
    """

    mean: np.ndarray
    cov: np.ndarray
    draws: np.ndarray
    n_posterior: int
    measurement_noise_cov: np.ndarray
    process_noise: dict
    input_noise: dict
    linear: list


@dataclass(frozen=True)
class ObserverExport:
    """Result of :func:`observer_inputs` (plain data; :mod:`tembayes.export.formats` writes it).

    Attributes
    ----------
    parameters : tuple of str
        Order of ``mean``, ``cov``, ``draws`` and the sensitivities.
    units : dict
        Parameter -> unit.
    modules : dict
        Module id (and ``"population"``) -> :class:`ModuleExport`.
    states : tuple of str
        The linear models' states (node names).
    inputs, outputs : tuple of str
        The linear models' inputs and outputs, named by their CSV columns.
    input_units, output_units : tuple of str
        Units of their values.
    meta : dict
        Run, batch, seed, points, the calibrated range, the warnings.
    """

    parameters: tuple
    units: dict
    modules: dict
    states: tuple
    inputs: tuple
    outputs: tuple
    input_units: tuple
    output_units: tuple
    meta: dict = field(default_factory=dict)

    @property
    def warnings(self):
        """What the export extrapolates (``meta.warnings``)."""
        return list(self.meta.get("warnings", []))


@dataclass(frozen=True)
class _Operating:
    """Where the linear models are taken: the calibration rig, the points ``(T̄ [degC], I [A])``, the room [degC]."""

    rig: object
    points: tuple
    room_C: float
    say: object


def measurement_noise_cov(exp, step_guard=5):
    """Covariance of the white sensor noise of an experiment, ``(ns + 1, ns + 1)`` (its sensors in K, V in V).

    Parameters
    ----------
    exp : tembayes.data.Experiment
    step_guard : int
        Samples left out on either side of a current step (the voltage jumps there).
    """
    Y = np.vstack([np.asarray(exp.sensors, float), np.asarray(exp.voltage, float)[None]])
    sd = np.array([noise_estimate(y) for y in Y])
    d2 = np.diff(Y, n=2, axis=1)
    di = np.abs(np.diff(np.asarray(exp.current, float)))
    jumps = np.flatnonzero(di > 20 * max(noise_estimate(exp.current), 1e-6))
    keep = np.ones(d2.shape[1], bool)
    for j in jumps:
        keep[max(j - step_guard, 0) : j + step_guard] = False
    d2 = d2[:, keep]
    # robust: drop any sample beyond 5 robust sds in any channel, then correlations
    ok = np.all(np.abs(d2) <= 5 * np.sqrt(6) * sd[:, None], axis=0)
    corr = np.corrcoef(d2[:, ok]) if ok.sum() > 10 else np.eye(len(Y))
    corr = np.where(np.isfinite(corr), corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    return corr * np.outer(sd, sd)


def _ou_noise(sd, tau, source, channels):
    """``process_noise``: an OU disturbance per output, ``q_continuous`` the spectral density of its drive."""
    sd, tau = np.asarray(sd, float), np.asarray(tau, float)
    return {
        "sd": sd,
        "tau_s": tau,
        "q_continuous": spectral_density(sd, tau),
        "source": source,
        "channels": list(channels),
    }


def _process_noise(t, residual, floor, source, channels):
    """OU disturbances fitted to residuals ``(nch, n)`` with the sensors' white noise ``floor`` ``(nch,)`` modelled."""
    fits = [fit_ou(t, residual[c], white_sd=floor[c]) for c in range(len(residual))]
    return _ou_noise([f.sd for f in fits], [f.tau_s for f in fits], source, channels)


#: Lower edges of the bins of time since the last current step [s] (the last bin is open).
STEP_BINS_S = (0.0, 10.0, 30.0, 100.0, 300.0)


def time_since_step(t, current):
    """Seconds since the last current step at every sample (inf before the first).

    A step is a change between samples of more than 20 times the current's
    white-noise level (as in :func:`measurement_noise_cov`).
    """
    t, current = np.asarray(t, float), np.asarray(current, float)
    jumps = np.flatnonzero(np.abs(np.diff(current)) > 20 * max(noise_estimate(current), 1e-6)) + 1
    last = np.searchsorted(jumps, np.arange(len(t)), side="right") - 1
    return np.where(last >= 0, t - t[jumps[np.maximum(last, 0)]], np.inf)


def disturbance_structure(t, residual, current, R):
    """How the model discrepancy varies with the time since a step, and across the outputs.

    Parameters
    ----------
    t : ndarray, shape (n,)
    residual : ndarray, shape (nch, n)
        Held-out residuals (measurement minus predictive mean).
    current : ndarray, shape (n,)
    R : ndarray, shape (nch, nch)
        White measurement-noise covariance.

    Returns
    -------
    dict
        ``sd_by_time_since_step`` ``(nch, len(STEP_BINS_S))``: the residual's
        RMS beyond the white noise in each bin of time since the last step
        (NaN with fewer than 30 samples); ``corr`` ``(nch, nch)``: correlation of
        the disturbances across the outputs (residual covariance minus the
        white noise, made positive semi-definite) and ``corr_by_time_since_step``
        ``(len(STEP_BINS_S), nch, nch)`` the same per bin (the transients dominate
        the pooled one); ``n_by_time_since_step``: samples per bin (the
        profile's sampling error: a 4-hour run with 20 steps has ~200 samples
        in the first bin); ``step_bins_s``.
    """
    since = time_since_step(t, current)
    edges = np.append(np.asarray(STEP_BINS_S, float), np.inf)
    white = np.diag(R)
    nb, nc = len(STEP_BINS_S), len(residual)
    prof = np.full((nc, nb), np.nan)
    corr_b = np.full((nb, nc, nc), np.nan)
    counts = np.zeros(nb, int)
    for b in range(nb):
        sel = (since >= edges[b]) & (since < edges[b + 1])
        counts[b] = int(sel.sum())
        if sel.sum() >= 30:
            prof[:, b] = np.sqrt(np.maximum(np.mean(residual[:, sel] ** 2, axis=1) - white, 0.0))
            corr_b[b] = _disturbance_corr(residual[:, sel] @ residual[:, sel].T / sel.sum() - R)
    return {
        "sd_by_time_since_step": prof,
        "corr": _disturbance_corr(np.cov(residual) - R),
        "corr_by_time_since_step": corr_b,
        "n_by_time_since_step": counts,
        "step_bins_s": np.array(STEP_BINS_S),
    }


def _disturbance_corr(C):
    """Correlation matrix of a disturbance covariance estimate, made positive semi-definite."""
    d = np.sqrt(np.maximum(np.diag(C), 1e-30))
    corr = np.clip(C / np.outer(d, d), -1.0, 1.0)
    w, V = np.linalg.eigh(corr)
    corr = (V * np.maximum(w, 1e-9)) @ V.T  # nearest positive semi-definite, unit diagonal again
    s = np.sqrt(np.diag(corr))
    return corr / np.outer(s, s)


def input_noise(exps):
    """The current's uncertainty as an observer sees it, from the runs given.

    ``current_sd_A``: white noise of the measured current; ``sample_interval_s``:
    the median sampling interval; ``step_instant``: a step happens at an
    unknown instant within its sampling interval, uniform a priori, so over
    the interval that holds a step of size dI the applied current is
    uncertain by ``dI^2 / 12`` in variance.  The instant's *phase* is common
    to the steps of one run (one sampling clock), so on a given run the
    realised error is one draw of it, and the held-out profile
    ``sd_by_time_since_step`` already holds that run's draw: a filter that
    adds this prior per step need not subtract it from the profile.
    """
    dts = np.concatenate([np.diff(np.asarray(e.time, float)) for e in exps])
    return {
        "current_sd_A": float(np.median([noise_estimate(e.current) for e in exps])),
        "sample_interval_s": float(np.median(dts)),
        "step_instant": "uniform within the sampling interval, one phase per run (one clock): current "
        "variance dI^2/12 over the interval holding a step of dI; the held-out profile "
        "already contains that run's realised phase",
    }


def observer_inputs(
    run,
    batch,
    *,
    points=None,
    room_C=None,
    allow_extrapolation=False,
    n_draws=200,
    seed=0,
    modules=None,
    heldout=True,
    progress=None,
):
    """Posterior moments, noise and linearised models of a calibration run for observer design.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
    batch : tembayes.data.Batch
        The calibrated batch (its identification runs anchor the rig, give
        the sensor noise and the calibrated range; its validation runs, if
        any, the process noise).
    points : sequence of (float, float), optional
        Operating points ``(T̄ [degC], I [A])`` to linearise at; default
        :func:`~tembayes.export.coverage.default_points` of the calibrated range.
    room_C : float, optional
        Temperature of the room the rig leaks to at the operating points
        [degC] (:func:`~tembayes.export.linearise.linearise`); default its
        median over the modules' identification runs.
    allow_extrapolation : bool
        Export points outside the calibrated range (with a warning in
        ``meta.warnings``) instead of refusing them.
    n_draws : int
        Posterior draws kept per module (evenly thinned).
    seed : int
        Seeds the held-out predictive (process noise) and the population's rig draws.
    modules : sequence of str, optional
        Default: every module of the run.
    heldout : bool or sequence of str
        Fit the process noise on the held-out runs where there are any
        (True: every validation run; a sequence: only the runs of these file
        names, e.g. ``["validation.csv"]``, so that another run stays unseen
        for checking an observer; False: the identification run's residuals).
    progress : callable, optional

    Returns
    -------
    ObserverExport

    Raises
    ------
    DataError
        An unknown module or held-out run, or a point outside the calibrated
        range without ``allow_extrapolation`` (before any work is done).
    """
    t0 = _time.perf_counter()
    say = progress or (lambda msg: None)
    rig = run.rig_for(batch)
    ids = list(modules) if modules else list(run.module_ids)
    bad = [m for m in ids if m not in run.module_ids]
    if bad:
        raise DataError(run.path, f"has no module(s) {bad}", f"Choose from {list(run.module_ids)}.")
    chosen = {mid: _heldout_runs(batch.modules[mid], heldout) for mid in ids}
    covered = calibrated_range(run, batch, modules=ids)
    points = default_points(covered) if points is None else tuple(tuple(map(float, p)) for p in points)
    warned = check_points(points, covered=covered, allow_extrapolation=allow_extrapolation)
    room = rig.layout.room
    if room_C is None:
        room_C = float(np.median(np.concatenate([batch.modules[m].identification.channel(room) for m in ids]))) - KELVIN
    ctx = _Operating(rig=rig, points=points, room_C=float(room_C), say=say)
    out, draws_by_id, names = {}, {}, None
    for mid in ids:
        say(f"{mid}: anchoring the rig on the identification run")
        d = module_draws(run, mid, batch.modules[mid].identification, rig)
        names = names or tuple(MODULE_PARAMETERS) + tuple(k for k in rig.parameter_names if k in d.params)
        draws_by_id[mid] = np.column_stack([np.asarray(d.params[k], float) for k in names])
        out[mid] = _module_export(
            run, batch, mid, d, draws_by_id[mid], names, chosen[mid], n_draws=n_draws, seed=seed, ctx=ctx
        )
    pop = run.population_draws(MODULE_PARAMETERS)
    if pop is not None:
        out["population"] = _population_export(pop, out, draws_by_id, names, n_draws=n_draws, seed=seed, ctx=ctx)
    warned += boundary_warnings(
        [m.linear for m in out.values()],
        covered=covered,
        room_C=float(room_C),
        room=room,
        controlled=rig.layout.controlled,
    )
    units = {**{p.name: p.unit for p in rig.parameters}, **MODULE_UNITS}
    meta = {
        "run": str(run.path),
        "batch": str(batch.path),
        "seed": int(seed),
        "room_C": float(room_C),
        "room_column": room,
        "points": [list(p) for p in points],
        "tref_C": run.tref_C,
        "calibrated_range": covered.to_dict(),
        "allow_extrapolation": bool(allow_extrapolation),
        "warnings": warned,
        "seconds": _time.perf_counter() - t0,
    }
    states = next(iter(out.values())).linear[0].states
    inputs, input_units, outputs, output_units = io_names(rig)
    return ObserverExport(
        names,
        {k: units.get(k, "") for k in names},
        out,
        states,
        inputs=inputs,
        outputs=outputs,
        input_units=input_units,
        output_units=output_units,
        meta=meta,
    )


def _module_export(run, batch, mid, d, X, names, heldout_runs, *, n_draws, seed, ctx):
    """One calibrated module's :class:`ModuleExport` from its anchored predictive draws ``d`` (``X`` over ``names``)."""
    module = batch.modules[mid]
    R = measurement_noise_cov(module.identification)
    floor = np.sqrt(np.diag(R))
    if heldout_runs:
        ctx.say(f"{mid}: process noise from the held-out run(s)")
        pn = _heldout_process_noise(run, batch, mid, heldout_runs, R, seed=seed)
    else:
        pn = _ou_noise(
            np.sqrt(np.maximum(d.noise_sd[0] ** 2 - floor**2, 0.0)),
            d.noise_tau[0],
            "identification-run residuals (the module has no held-out run)",
            io_names(ctx.rig)[2],
        )
    mean = X.mean(axis=0)
    return ModuleExport(
        mean=mean,
        cov=np.cov(X, rowvar=False),
        draws=thin(X, n_draws),
        n_posterior=len(X),
        measurement_noise_cov=R,
        process_noise=pn,
        input_noise=input_noise(heldout_runs or [module.identification]),
        linear=_linear_models(dict(zip(names, mean)), names, mid, ctx),
    )


def _heldout_process_noise(run, batch, mid, runs, R, *, seed):
    """Process noise and its structure from the posterior-predictive residuals of held-out runs."""
    ts, rs, cs = [], [], []
    for exp in runs:
        p = predict(run, exp, mid, batch, n_draws=HELDOUT_DRAWS, seed=seed, compare_constant=False).linear
        ts.append(p.time)
        rs.append(p.residual)
        cs.append(np.asarray(p.current, float))
    # runs are joined end to end; the one spurious innovation at a seam is negligible
    t = np.concatenate([ts[0]] + [ts[i] - ts[i][0] + ts[i - 1][-1] + 1.0 for i in range(1, len(ts))])
    pn = _process_noise(
        t,
        np.concatenate(rs, axis=1),
        np.sqrt(np.diag(R)),
        "held-out posterior-predictive residuals: " + ", ".join(Path(str(e.path)).name for e in runs),
        p.channels,
    )
    # per run (the time since a step restarts with each run), then pooled by sample count
    parts = [disturbance_structure(tt, rr, cc, R) for tt, rr, cc in zip(ts, rs, cs)]
    pn.update(_pool_structure(parts, weights=np.array([len(tt) for tt in ts], float)))
    return pn


def _population_export(pop, out, draws_by_id, names, *, n_draws, seed, ctx):
    """A new unit of the batch: the population's law draws ``pop``, the rig as the calibrated modules' (pooled)."""
    ids = list(draws_by_id)
    rigX = np.vstack([draws_by_id[m][:, len(MODULE_PARAMETERS) :] for m in ids])
    rigX = rigX[np.random.default_rng(seed).integers(0, len(rigX), len(pop))]
    X = np.hstack([pop, rigX])
    mean = X.mean(axis=0)
    ctx.say("population: linearising a new module of the batch")
    return ModuleExport(
        mean=mean,
        cov=np.cov(X, rowvar=False),
        draws=thin(X, n_draws),
        n_posterior=len(X),
        measurement_noise_cov=np.mean([out[m].measurement_noise_cov for m in ids], axis=0),
        process_noise=_pool_process_noise([out[m].process_noise for m in ids]),
        input_noise=out[ids[0]].input_noise,
        linear=_linear_models(dict(zip(names, mean)), names, "population", ctx),
    )


def _heldout_runs(module, heldout):
    """The module's validation runs chosen by ``heldout`` (True, False or file names)."""
    if heldout is True or heldout is False:
        return list(module.validations) if heldout else []
    names = {Path(str(e.path)).name: e for e in module.validations}
    missing = [n for n in heldout if n not in names]
    if missing:
        raise DataError(
            module.path,
            f"has no validation run(s) {missing}",
            f"Choose from {sorted(names)} (file names), or leave out --heldout.",
        )
    return [names[n] for n in heldout]


def _linear_models(params, names, label, ctx):
    """The rig of ``params`` linearised at every operating point of ``ctx``, sensitive to ``names``."""
    lin = []
    for tavg, current in ctx.points:
        ctx.say(f"{label}: linearising at T_avg {tavg:g} C, I {current:g} A")
        lin.append(linearise(params, ctx.rig, tavg, current, room_C=ctx.room_C, sensitivity=names))
    return lin


def _pool_process_noise(items):
    pn = _ou_noise(
        np.sqrt(np.mean([p["sd"] ** 2 for p in items], axis=0)),
        np.mean([p["tau_s"] for p in items], axis=0),
        "mean over the calibrated modules",
        items[0]["channels"],
    )
    if all("corr" in p for p in items):
        pn.update(_pool_structure(items))
    return pn


def _pool_structure(parts, weights=None):
    """The :func:`disturbance_structure` keys pooled over runs or modules (``corr`` weighted)."""
    return {
        "corr": np.average([q["corr"] for q in parts], axis=0, weights=weights),
        "sd_by_time_since_step": np.sqrt(np.nanmean([q["sd_by_time_since_step"] ** 2 for q in parts], axis=0)),
        "corr_by_time_since_step": np.nanmean([q["corr_by_time_since_step"] for q in parts], axis=0),
        "n_by_time_since_step": np.sum([q["n_by_time_since_step"] for q in parts], axis=0),
        "step_bins_s": np.array(STEP_BINS_S),
    }
