"""Uncertainty inputs for observer design (``tembayes export``).

Per calibrated module, and for a new module of the batch (the population):

- the posterior mean and covariance of the laws, ``K`` and the rig
  parameters (the rig anchored on the identification run, as ``tembayes
  predict`` does), and a thinned set of posterior draws (for a UKF's sigma
  points or a robust design's scenarios);
- the sensors' measurement-noise covariance (T1..T4, V), read off the
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

from tembayes.constants import MODULE_PARAMETERS
from tembayes.data.quality import noise_estimate
from tembayes.errors import DataError
from tembayes.export.linearise import INPUTS, OUTPUTS, linearise
from tembayes.predict.predictive import module_draws, predict
from tembayes.predict.runmodel import CHANNELS

#: Schema name and version of the export (``schema`` key of every format).
SCHEMA = "tembayes-observer-export/1"
#: Default operating points ``(T̄ [degC], I [A])``.
DEFAULT_POINTS = ((25.0, 0.0), (25.0, 2.0), (40.0, 4.0))


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
        Module id (and ``"population"``) -> ``{"mean", "cov", "draws",
        "measurement_noise_cov", "process_noise", "linear": [LinearModel]}``.
    states, inputs, outputs : tuple of str
    meta : dict
        Run, seed, command context.
    """

    parameters: tuple
    units: dict
    modules: dict
    states: tuple
    inputs: tuple = INPUTS
    outputs: tuple = OUTPUTS
    meta: dict = field(default_factory=dict)


def measurement_noise_cov(exp, step_guard=5):
    """Covariance of the white sensor noise of an experiment, ``(5, 5)`` (T1..T4 in K, V in V).

    Parameters
    ----------
    exp : tembayes.data.Experiment
    step_guard : int
        Samples left out on either side of a current step (the voltage jumps there).
    """
    Y = np.vstack([np.asarray(exp.sensors[c], float) for c in range(4)] + [np.asarray(exp.voltage, float)])
    sd = np.array([noise_estimate(y) for y in Y])
    d2 = np.diff(Y, n=2, axis=1)
    di = np.abs(np.diff(np.asarray(exp.current, float)))
    jumps = np.flatnonzero(di > 20 * max(noise_estimate(exp.current), 1e-6))
    keep = np.ones(d2.shape[1], bool)
    for j in jumps:
        keep[max(j - step_guard, 0):j + step_guard] = False
    d2 = d2[:, keep]
    # robust: drop any sample beyond 5 robust sds in any channel, then correlations
    ok = np.all(np.abs(d2) <= 5 * np.sqrt(6) * sd[:, None], axis=0)
    corr = np.corrcoef(d2[:, ok]) if ok.sum() > 10 else np.eye(5)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    return corr * np.outer(sd, sd)


def fit_ou_plus_white(t, r, white_sd, *, taus=np.geomspace(1.0, 2e4, 48), n_sd=48):
    """Maximum-likelihood OU disturbance under known white noise: ``r = d + v``, ``v ~ N(0, white_sd^2)``.

    A scalar Kalman filter, vectorised over a grid of ``(tau, sd)``; a plain
    OU fit would spend its correlation time on the white noise (taus of a
    second on a 1 Hz residual).

    Returns
    -------
    (sd, tau_s) : float, float
        Stationary sd of ``d`` (0 when the residual is white) [unit of r], its correlation time [s].
    """
    r = np.asarray(r, float)
    rv = float(white_sd) ** 2
    top = max(np.std(r), 1e-12)
    sds = np.concatenate([[0.0], np.geomspace(top * 1e-3, top * 2.0, n_sd - 1)])
    tau, sd = (a.ravel() for a in np.meshgrid(taus, sds, indexing="ij"))
    q = sd * sd
    m, P = np.zeros_like(q), q.copy()
    ll = np.zeros_like(q)
    dt = np.diff(t, prepend=t[0])
    for k in range(len(r)):
        phi = np.exp(-dt[k] / tau)
        m = phi * m
        P = phi * phi * P + q * (1.0 - phi * phi)
        S = P + rv
        e = r[k] - m
        ll -= 0.5 * (np.log(S) + e * e / S)
        g = P / S
        m = m + g * e
        P = (1.0 - g) * P
    i = int(np.argmax(ll))
    return float(sd[i]), float(tau[i])


def _ou_noise(sd, tau, source):
    """``process_noise``: an OU disturbance per output, ``q = 2 sd^2 / tau`` the spectral density of its drive."""
    sd, tau = np.asarray(sd, float), np.asarray(tau, float)
    return {"sd": sd, "tau_s": tau, "q_continuous": 2.0 * sd ** 2 / tau, "source": source,
            "channels": list(CHANNELS)}


def _process_noise(t, residual, floor, source):
    fits = [fit_ou_plus_white(t, residual[c], floor[c]) for c in range(len(CHANNELS))]
    return _ou_noise([f[0] for f in fits], [f[1] for f in fits], source)


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
    residual : ndarray, shape (5, n)
        Held-out residuals (measurement minus predictive mean).
    current : ndarray, shape (n,)
    R : ndarray, shape (5, 5)
        White measurement-noise covariance.

    Returns
    -------
    dict
        ``sd_by_time_since_step`` ``(5, len(STEP_BINS_S))``: the residual's
        RMS beyond the white noise in each bin of time since the last step
        (NaN with fewer than 30 samples); ``corr`` ``(5, 5)``: correlation of
        the disturbances across the outputs (residual covariance minus the
        white noise, made positive semi-definite) and ``corr_by_time_since_step``
        ``(len(STEP_BINS_S), 5, 5)`` the same per bin (the transients dominate
        the pooled one); ``n_by_time_since_step``: samples per bin (the
        profile's sampling error: a 4-hour run with 20 steps has ~200 samples
        in the first bin); ``step_bins_s``.
    """
    since = time_since_step(t, current)
    edges = np.append(np.asarray(STEP_BINS_S, float), np.inf)
    white = np.diag(R)
    nb, nc = len(STEP_BINS_S), len(CHANNELS)
    prof = np.full((nc, nb), np.nan)
    corr_b = np.full((nb, nc, nc), np.nan)
    counts = np.zeros(nb, int)
    for b in range(nb):
        sel = (since >= edges[b]) & (since < edges[b + 1])
        counts[b] = int(sel.sum())
        if sel.sum() >= 30:
            prof[:, b] = np.sqrt(np.maximum(np.mean(residual[:, sel] ** 2, axis=1) - white, 0.0))
            corr_b[b] = _disturbance_corr(residual[:, sel] @ residual[:, sel].T / sel.sum() - R)
    return {"sd_by_time_since_step": prof, "corr": _disturbance_corr(np.cov(residual) - R),
            "corr_by_time_since_step": corr_b, "n_by_time_since_step": counts, "step_bins_s": np.array(STEP_BINS_S)}


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
    return {"current_sd_A": float(np.median([noise_estimate(e.current) for e in exps])),
            "sample_interval_s": float(np.median(dts)),
            "step_instant": "uniform within the sampling interval, one phase per run (one clock): current "
                            "variance dI^2/12 over the interval holding a step of dI; the held-out profile "
                            "already contains that run's realised phase"}


def observer_inputs(run, batch, *, points=DEFAULT_POINTS, t_amb_C=25.0, n_draws=200, seed=0, modules=None,
                    heldout=True, progress=None):
    """Posterior moments, noise and linearised models of a calibration run for observer design.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
    batch : tembayes.data.Batch
        The calibrated batch (its identification runs anchor the rig and give
        the sensor noise; its validation runs, if any, the process noise).
    points : sequence of (float, float)
        Operating points ``(T̄ [degC], I [A])`` to linearise at.
    t_amb_C : float
        Ambient temperature of the operating points [degC].
    n_draws : int
        Posterior draws kept per module (evenly thinned).
    seed : int
        Seeds the held-out predictive (process noise).
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
    """
    t0 = _time.perf_counter()
    say = progress or (lambda msg: None)
    rig = run.rig_for(batch)
    ids = list(modules) if modules else list(run.module_ids)
    bad = [m for m in ids if m not in run.module_ids]
    if bad:
        raise DataError(run.path, f"has no module(s) {bad}", f"Choose from {list(run.module_ids)}.")
    chosen = {mid: _heldout_runs(batch.modules[mid], heldout) for mid in ids}  # refused before any work
    names, out, states = None, {}, None
    per_params = {}
    for mid in ids:
        module = batch.modules[mid]
        say(f"{mid}: anchoring the rig on the identification run")
        d = module_draws(run, mid, module.identification, rig)
        if names is None:
            names = tuple(MODULE_PARAMETERS) + tuple(k for k in rig.parameter_names if k in d.params)
        X = np.column_stack([np.asarray(d.params[k], float) for k in names])
        per_params[mid] = X
        keep = _thin(X, n_draws)
        R = measurement_noise_cov(module.identification)
        floor = np.sqrt(np.diag(R))
        vals = chosen[mid]
        if vals:
            say(f"{mid}: process noise from the held-out run(s)")
            ts, rs, cs = [], [], []
            for exp in vals:
                p = predict(run, exp, mid, batch, n_draws=100, seed=seed, compare_constant=False).linear
                ts.append(p.time)
                rs.append(p.residual)
                cs.append(np.asarray(p.current, float))
            # runs are joined end to end; the one spurious innovation at a seam is negligible
            t = np.concatenate([ts[0]] + [ts[i] - ts[i][0] + ts[i - 1][-1] + 1.0 for i in range(1, len(ts))])
            pn = _process_noise(t, np.concatenate(rs, axis=1), floor,
                                "held-out posterior-predictive residuals: "
                                + ", ".join(Path(str(e.path)).name for e in vals))
            # per run (the time since a step restarts with each run), then pooled by sample count
            parts = [disturbance_structure(tt, rr, cc, R) for tt, rr, cc in zip(ts, rs, cs)]
            wts = np.array([len(tt) for tt in ts], float)
            pn.update(_pool_structure(parts, weights=wts))
        else:
            pn = _ou_noise(np.sqrt(np.maximum(d.noise_sd[0] ** 2 - floor ** 2, 0.0)), d.noise_tau[0],
                           "identification-run residuals (the module has no held-out run)")
        mean = X.mean(axis=0)
        lin = _linear_models(dict(zip(names, mean)), rig, points, t_amb_C, names, say, mid)
        states = lin[0].states
        out[mid] = {"mean": mean, "cov": np.cov(X, rowvar=False), "draws": keep, "measurement_noise_cov": R,
                    "process_noise": pn, "input_noise": input_noise(vals or [module.identification]),
                    "linear": lin, "n_posterior": len(X)}
    pop = run.population_draws(MODULE_PARAMETERS)
    if pop is not None:
        # a new unit: the population's laws, the rig as the calibrated modules' (their pooled draws)
        rigX = np.vstack([per_params[m][:, len(MODULE_PARAMETERS):] for m in ids])
        rng = np.random.default_rng(seed)
        rigX = rigX[rng.integers(0, len(rigX), len(pop))]
        X = np.hstack([pop, rigX])
        mean = X.mean(axis=0)
        say("population: linearising a new module of the batch")
        out["population"] = {"mean": mean, "cov": np.cov(X, rowvar=False),
                             "draws": _thin(X, n_draws),
                             "measurement_noise_cov": np.mean([out[m]["measurement_noise_cov"] for m in ids], axis=0),
                             "process_noise": _pool_process_noise([out[m]["process_noise"] for m in ids]),
                             "input_noise": out[ids[0]]["input_noise"],
                             "linear": _linear_models(dict(zip(names, mean)), rig, points, t_amb_C, names, say,
                                                      "population"),
                             "n_posterior": len(X)}
    units = {p.name: p.unit for p in rig.parameters}
    units.update({"R0_ohm": "ohm", "R1_ohm_per_K": "ohm/K", "S0_V_per_K": "V/K", "S1_V_per_K2": "V/K^2",
                  "K_W_per_K": "W/K"})
    meta = {"run": str(run.path), "batch": str(batch.path), "seed": int(seed), "t_amb_C": float(t_amb_C),
            "points": [list(map(float, p)) for p in points], "tref_C": run.tref_C,
            "seconds": _time.perf_counter() - t0}
    return ObserverExport(names, {k: units.get(k, "") for k in names}, out, states, meta=meta)


def _heldout_runs(module, heldout):
    """The module's validation runs chosen by ``heldout`` (True, False or file names)."""
    if heldout is True or heldout is False:
        return list(module.validations) if heldout else []
    names = {Path(str(e.path)).name: e for e in module.validations}
    missing = [n for n in heldout if n not in names]
    if missing:
        raise DataError(module.path, f"has no validation run(s) {missing}",
                        f"Choose from {sorted(names)} (file names), or leave out --heldout.")
    return [names[n] for n in heldout]


def _thin(X, n):
    """At most ``n`` rows of ``X``, evenly spaced."""
    return X[np.linspace(0, len(X) - 1, min(n, len(X))).round().astype(int)]


def _linear_models(params, rig, points, t_amb_C, names, say, label):
    lin = []
    for tavg, current in points:
        say(f"{label}: linearising at T_avg {tavg:g} C, I {current:g} A")
        lin.append(linearise(params, rig, tavg, current, t_amb_C=t_amb_C, sensitivity=names))
    return lin


def _pool_process_noise(items):
    pn = _ou_noise(np.sqrt(np.mean([p["sd"] ** 2 for p in items], axis=0)),
                   np.mean([p["tau_s"] for p in items], axis=0), "mean over the calibrated modules")
    if all("corr" in p for p in items):
        pn.update(_pool_structure(items))
    return pn


def _pool_structure(parts, weights=None):
    """The :func:`disturbance_structure` keys pooled over runs or modules (``corr`` weighted)."""
    return {"corr": np.average([q["corr"] for q in parts], axis=0, weights=weights),
            "sd_by_time_since_step": np.sqrt(np.nanmean([q["sd_by_time_since_step"] ** 2 for q in parts], axis=0)),
            "corr_by_time_since_step": np.nanmean([q["corr_by_time_since_step"] for q in parts], axis=0),
            "n_by_time_since_step": np.sum([q["n_by_time_since_step"] for q in parts], axis=0),
            "step_bins_s": np.array(STEP_BINS_S)}
