"""Posterior-predictive simulation of an experiment (``tembayes predict``).

The pipeline, each step a plain function of the previous one's result:

1. :func:`module_draws` -- a module's step-posterior draws from the run, the
   rig parameters the step likelihood leaves unpinned anchored on its
   identification run (:func:`~tembayes.predict.anchor.anchor_rig`), which
   also fits each channel's residual process (the predictive noise);
   :func:`population_draws` -- the same for a *new* unit of the batch: laws
   and K from the population predictive, the rig (paste, plates, leaks) and
   the noise of a random calibrated module (a new mount in the same rig);
2. :func:`constant_laws` -- optionally, R and S frozen at T-bar = 35 degC (the
   paper's Figure 8 model), re-anchored with K free (its own rig fit);
3. :func:`simulate_predictive` -- every draw simulated through the experiment,
   driven by the measured current levels, water and ambient temperatures
   (:class:`~tembayes.predict.runmodel.RunModel`), each draw with its own step
   instant (the phase of a validation run's clock is unknown: uniform over
   the sampling interval), plus measurement noise and discrepancy from the
   residual processes, reduced to central 50/90/95 % bands per sample;
4. :meth:`Prediction.metrics` -- RMSE, max error and band coverage per
   channel (docs/outputs.md, 'metrics.json (predict)') and the errors binned by T-bar.

Everything is SI inside (K, V); ``metrics.json`` errors of the sensor
channels are in K, which equal degC differences.
"""

from __future__ import annotations

import time as _time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tembayes.common.seeds import stream
from tembayes.constants import KELVIN, MODULE_PARAMETERS, T_REF
from tembayes.errors import DataError, ModelError, TembayesError
from tembayes.physics import effects as E
from tembayes.physics.effects import EFFECT_PARAMETERS
from tembayes.predict.anchor import UNPINNED_FRACTION, anchor_rig, held_draws, unpinned
from tembayes.predict.runmodel import RunModel

#: Central band levels [%] (docs/outputs.md, 'metrics.json (predict)').
LEVELS = (50, 90, 95)
#: Temperature of the constant-law model [degC] (the paper's Figure 8).
CONSTANT_AT_C = 35.0
#: Width of the T-bar bins of the error summary [K].
TAVG_BIN_K = 5.0
#: Draws simulated at once (memory: ~60 MB per 100 draws of a 4 h run at 1 Hz).
CHUNK = 100
#: Largest fraction of predictive draws that may fail to simulate; they are left out and counted.
MAX_FAILED_FRACTION = 0.05


@dataclass(frozen=True)
class PredictiveDraws:
    """Parameter draws of a predictive and the noise that goes with them.

    Attributes
    ----------
    params : dict
        ``name -> (M,)`` simulation parameters (SI).
    noise_sd : ndarray, shape (M, 5)
        Sd of the residual process of each channel for each draw (K, V).
    label : str
        ``"TEM2"``, ``"population"``...
    laws : str
        ``"linear"`` or ``"constant"``.
    anchor : dict
        What the anchoring did (per module), for the record.
    noise_tau : ndarray, shape (M, 5), optional
        Correlation time of each channel's residual process [s].
    """

    params: dict
    noise_sd: np.ndarray
    label: str
    laws: str = "linear"
    anchor: dict = field(default_factory=dict)
    noise_tau: np.ndarray | None = None

    @property
    def n(self):
        """Number of draws."""
        return len(self.noise_sd)


def module_raw_draws(run, module_id):
    """``name -> (M,)`` every sampled parameter's posterior draws of a module of a run (SI)."""
    post = run.idata.posterior
    names = [k for k in post.data_vars]
    X = run.draws(module_id, names)
    return {k: X[:, j] for j, k in enumerate(names)}


def _sim_names(draws, rig):
    known = set(MODULE_PARAMETERS) | set(rig.parameter_names) | set(EFFECT_PARAMETERS)
    return [k for k in draws if k in known]


def module_draws(run, module_id, identification, rig, *, laws="linear"):
    """A calibrated module's predictive draws, anchored on its identification run.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
    module_id : str
    identification : tembayes.data.Experiment
        The module's identification run (the one it was calibrated on).
    rig : RigDescription
        The calibration rig.
    laws : {"linear", "constant"}
        ``"constant"``: R and S frozen at :data:`CONSTANT_AT_C` (then K is
        re-anchored too, as the paper refits its rig for that model).

    Returns
    -------
    PredictiveDraws
        All the module's draws (``chain x draw``).
    """
    if module_id not in run.module_ids:
        raise DataError(
            run.path / "posterior.nc",
            f"has no module '{module_id}'",
            f"Choose one of {list(run.module_ids)} or 'population'.",
        )
    return posterior_draws(
        module_raw_draws(run, module_id), run.priors(module_id), module_id, identification, rig, laws=laws
    )


def posterior_draws(raw, priors, label, identification, rig, *, laws="linear"):
    """Predictive draws of a module posterior given as draws and priors.

    The work behind :func:`module_draws`, for a posterior that is not in a
    calibration run (e.g. the gap diagnosis's recalibration with an effect
    added, whose effect parameters are anchored like the rig's when the step
    likelihood leaves them open).

    Parameters
    ----------
    raw : dict
        ``name -> (M,)`` posterior draws (SI).
    priors : dict
        ``name -> {"kind", "center", "scale"}``.
    label : str
    identification : tembayes.data.Experiment
    rig : RigDescription
    laws : {"linear", "constant"}

    Returns
    -------
    PredictiveDraws
    """
    if laws == "linear":
        held = held_draws(rig, raw, priors, label)
    else:
        # the constant laws' misfit is the paper model's to show, not the held parameters' to absorb:
        # they go back to the values the calibration held them at (their carried-over draws moved the linear laws)
        held = {}
        raw = {k: v for k, v in raw.items() if k in priors or k not in rig.parameter_names}
    raw = {**raw, **held}
    names = unpinned(raw, priors, rig) + tuple(held) + unpinned_effects(raw, priors)
    fixed = None
    if laws == "constant":
        raw = constant_laws(raw)
        fixed = {"R1_ohm_per_K": 0.0, "S1_V_per_K2": 0.0}
        names = tuple(names) + ("K_W_per_K",)
    elif laws != "linear":
        raise ValueError(f"laws must be 'linear' or 'constant', got {laws!r}")
    model = RunModel(identification, rig)
    a = anchor_rig(model, raw, names, fixed=fixed)
    params = {k: a.draws[k] for k in _sim_names(a.draws, rig)}
    for k in params:
        if k in EFFECT_PARAMETERS and E.CATALOGUE[EFFECT_PARAMETERS[k]].parameter(k).nonnegative:
            params[k] = np.maximum(params[k], 0.0)
    sd = np.array([a.residual[c].sd for c in model.channels])
    tau = np.array([a.residual[c].tau_s for c in model.channels])
    M = len(params["R0_ohm"])
    return PredictiveDraws(
        params=params,
        noise_sd=np.repeat(sd[None], M, axis=0),
        label=label,
        laws=laws,
        anchor={label: {"updated": list(names), **a.to_dict()}},
        noise_tau=np.repeat(tau[None], M, axis=0),
    )


def unpinned_effects(draws, priors, fraction=UNPINNED_FRACTION):
    """Effect parameters the step likelihood leaves near their prior (see :func:`unpinned`)."""
    out = []
    for k in EFFECT_PARAMETERS:
        if k not in draws or k not in priors:
            continue
        pr = priors[k]
        prior_sd = float(pr["scale"]) / np.sqrt(3.0) if pr["kind"] == "uniform" else float(pr["scale"])
        if np.std(np.asarray(draws[k], float)) > fraction * prior_sd:
            out.append(k)
    return tuple(out)


def constant_laws(draws, at_C=CONSTANT_AT_C):
    """Draws with R and S frozen at their value at ``at_C`` [degC] (slopes zero)."""
    x = at_C + KELVIN - T_REF
    out = dict(draws)
    out["R0_ohm"] = np.asarray(draws["R0_ohm"]) + np.asarray(draws["R1_ohm_per_K"]) * x
    out["S0_V_per_K"] = np.asarray(draws["S0_V_per_K"]) + np.asarray(draws["S1_V_per_K2"]) * x
    out["R1_ohm_per_K"] = np.zeros_like(out["R0_ohm"])
    out["S1_V_per_K2"] = np.zeros_like(out["S0_V_per_K"])
    return out


def population_draws(run, module_draws_by_id, rng, n):
    """Predictive draws for a new unit of the batch.

    Laws and K come from the run's population predictive (``summary.json``'s
    ``population``); every other simulation parameter and the noise from a
    draw of a randomly chosen calibrated module (the same rig, a new mount).

    Parameters
    ----------
    run : CalibrationRun
    module_draws_by_id : dict
        ``module id -> PredictiveDraws`` (linear laws).
    rng : numpy.random.Generator
    n : int

    Returns
    -------
    PredictiveDraws
    """
    pop = run.population_draws(MODULE_PARAMETERS)
    if pop is None:
        raise DataError(
            run.path / "posterior.nc",
            "has no population fit",
            "Calibrate the whole batch (the population needs at least two modules).",
        )
    rows = rng.choice(len(pop), size=n, replace=len(pop) < n)
    ids = list(module_draws_by_id)
    which = rng.integers(len(ids), size=n)
    params = {k: pop[rows, j] for j, k in enumerate(MODULE_PARAMETERS)}
    rig_names = [k for k in module_draws_by_id[ids[0]].params if k not in MODULE_PARAMETERS]
    out = {k: np.empty(n) for k in rig_names}
    nch = module_draws_by_id[ids[0]].noise_sd.shape[1]
    noise = np.empty((n, nch))
    tau = np.empty((n, nch))
    for i, mid in enumerate(ids):
        sel = np.flatnonzero(which == i)
        d = module_draws_by_id[mid]
        pick = rng.integers(d.n, size=len(sel))
        for k in rig_names:
            out[k][sel] = d.params[k][pick]
        noise[sel] = d.noise_sd[pick]
        tau[sel] = d.noise_tau[pick] if d.noise_tau is not None else 0.0
    params.update(out)
    anchor = {}
    for d in module_draws_by_id.values():
        anchor.update(d.anchor)
    return PredictiveDraws(params=params, noise_sd=noise, label="population", anchor=anchor, noise_tau=tau)


def subsample(draws, rng, n):
    """``n`` draws of a :class:`PredictiveDraws` (without replacement when there are enough)."""
    idx = rng.choice(draws.n, size=n, replace=draws.n < n)
    return PredictiveDraws(
        params={k: np.asarray(v)[idx] for k, v in draws.params.items()},
        noise_sd=draws.noise_sd[idx],
        label=draws.label,
        laws=draws.laws,
        anchor=draws.anchor,
        noise_tau=None if draws.noise_tau is None else draws.noise_tau[idx],
    )


@dataclass(frozen=True)
class Prediction:
    """A posterior-predictive of one experiment (SI).

    Attributes
    ----------
    source : str
        The experiment file.
    label : str
        Module id or ``"population"``.
    laws : str
        ``"linear"`` or ``"constant"``.
    time : ndarray, shape (n,)
        [s].
    channels : tuple of str
        The rig's sensor columns and ``voltage_V``
        (:attr:`~tembayes.predict.runmodel.RunModel.channels`).
    measured, mean, median : ndarray, shape (nch, n)
        Measured values, predictive mean and median (K for the sensors, V).
    bands : dict
        Level [%] -> ``(lower, upper)``, each ``(nch, n)``: the central band of
        the predictive (measurement noise included).
    tavg : ndarray, shape (n,)
        The measured mean of the two face sensors [K], the stand-in for
        T-bar in the error summary.
    current : ndarray, shape (n,)
        Measured current [A].
    n_draws : int
    seconds : float
        Wall time of the simulation and the bands.
    since_step : ndarray, shape (n,), optional
        Time since the last current step [s] (since the start before the first).
    deviations : ndarray, shape (M, nch, n), optional
        The draws' noise-free predictions minus ``mean`` (float32), kept with
        ``keep_draws=True`` for posterior-predictive checks.
    noise_sd, noise_tau : ndarray, shape (M, nch), optional
        The draws' residual processes (kept with ``keep_draws=True``).
    n_failed : int
        Draws the rig could not simulate, left out (at most
        :data:`MAX_FAILED_FRACTION` of them; ``n_draws`` counts the rest).
    start_current : float or None
        The pre-history current the run's initial state was taken from [A]
        (:meth:`~tembayes.predict.runmodel.RunModel.fit_start`).
    predictive : ndarray, shape (M, nch, n), optional
        Every draw's prediction with its noise, the values the bands are
        quantiles of (float32; kept with ``keep_predictive=True``).
    face : tuple of str
        The hot- and cold-face sensor columns (``tavg`` is their mean).
    labels : dict of str to str
        Channel -> a label for figures (where the sensor sits).
    """

    source: str
    label: str
    laws: str
    time: np.ndarray
    channels: tuple
    measured: np.ndarray
    mean: np.ndarray
    median: np.ndarray
    bands: dict
    tavg: np.ndarray
    current: np.ndarray
    n_draws: int
    seconds: float
    since_step: np.ndarray | None = None
    deviations: np.ndarray | None = None
    noise_sd: np.ndarray | None = None
    noise_tau: np.ndarray | None = None
    n_failed: int = 0
    start_current: float | None = None
    predictive: np.ndarray | None = None
    face: tuple = ()
    labels: dict = field(default_factory=dict)

    @property
    def residual(self):
        """Measured minus predictive mean, ``(nch, n)``."""
        return self.measured - self.mean

    def coverage(self, level):
        """Fraction of samples inside the central ``level`` % band, per channel ``(nch,)``."""
        lo, hi = self.bands[level]
        return np.mean((self.measured >= lo) & (self.measured <= hi), axis=1)

    def metrics(self):
        """``{channel: {rmse, max_abs, coverage50, coverage90, coverage95}}``.

        As in docs/outputs.md, 'metrics.json (predict)'.
        """
        r = self.residual
        cov = {lv: self.coverage(lv) for lv in LEVELS}
        return {
            ch: {
                "rmse": float(np.sqrt(np.mean(r[c] ** 2))),
                "max_abs": float(np.max(np.abs(r[c]))),
                **{f"coverage{lv}": float(cov[lv][c]) for lv in LEVELS},
            }
            for c, ch in enumerate(self.channels)
        }

    def by_tavg(self, width=TAVG_BIN_K, min_samples=30):
        """RMSE per channel in bins of T-bar (the measured mean of the face sensors).

        Returns
        -------
        list of dict
            ``{"Tavg_C_low", "Tavg_C_high", "n", "rmse": {channel: ...}}``,
            bins with fewer than ``min_samples`` samples left out.
        """
        tc = self.tavg - KELVIN
        edges = np.arange(np.floor(tc.min() / width) * width, tc.max() + width, width)
        out = []
        r = self.residual
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (tc >= lo) & (tc < hi)
            if m.sum() < min_samples:
                continue
            out.append(
                {
                    "Tavg_C_low": float(lo),
                    "Tavg_C_high": float(hi),
                    "n": int(m.sum()),
                    "rmse": {ch: float(np.sqrt(np.mean(r[c, m] ** 2))) for c, ch in enumerate(self.channels)},
                }
            )
        return out


def simulate_predictive(model, draws, rng, *, progress=None, keep_draws=False, keep_predictive=False, shift=None):
    """Simulate every draw through an experiment and form the bands.

    Parameters
    ----------
    model : RunModel
        The experiment.
    draws : PredictiveDraws
    rng : numpy.random.Generator
        Draws the step instants and the noise.
    progress : callable, optional
        Called with a message per chunk of draws.
    keep_draws : bool
        Keep the draws' predictions in the result (``deviations``), for
        posterior-predictive checks (:mod:`tembayes.gap`).
    keep_predictive : bool
        Keep the draws' predictions with noise (``predictive``), for
        :mod:`tembayes.predict.inference`.
    shift : float, optional
        The run's step phase [s] for every draw (e.g. taken from the run by
        :meth:`RunModel.fit_phase`); default: unknown, one drawn per draw.
        ``rng`` is advanced the same either way.

    Returns
    -------
    Prediction
    """
    t0 = _time.perf_counter()
    exp = model.exp
    M = draws.n
    n = len(model.time)
    if model.start == "data" and model.start_current is None:  # the run's initial state, from its first minute
        model.fit_start({k: float(np.median(v)) for k, v in draws.params.items()})
    Y = np.empty((M, len(model.channels), n))
    # one phase per draw, common to the run's steps (see RunModel), unless the run's is given
    drawn = rng.uniform(-1.0, 1.0, M) * model.shift_bound
    shift = drawn if shift is None else np.full(M, float(shift))
    for a in range(0, M, CHUNK):
        b = min(a + CHUNK, M)
        params = {k: np.asarray(v)[a:b] for k, v in draws.params.items()}
        sens, volt = model.simulate(params, shift[a:b], strict=False)  # a failed draw comes back NaN
        Y[a:b, :-1] = sens
        Y[a:b, -1] = volt
        if progress:
            progress(f"  predictive draws {b}/{M}")
    ok = np.all(np.isfinite(Y), axis=(1, 2))
    n_failed = int(M - ok.sum())
    if n_failed > MAX_FAILED_FRACTION * M:
        raise ModelError(
            f"the simulation of {exp.path} failed for {n_failed} of {M} draws (no steady start, step "
            f"budget exceeded or non-finite values); at most {MAX_FAILED_FRACTION:.0%} may fail"
        )
    noise_sd, noise_tau = draws.noise_sd, draws.noise_tau
    if n_failed:
        # a draw the rig cannot simulate (far in a posterior's tail) is left out and counted,
        # rather than discarding the other draws' bands
        warnings.warn(
            f"{exp.path}: {n_failed} of {M} predictive draws failed to simulate and are left out",
            RuntimeWarning,
            stacklevel=2,
        )
        Y, noise_sd = Y[ok], noise_sd[ok]
        noise_tau = None if noise_tau is None else noise_tau[ok]
    mean = Y.mean(axis=0)
    dev = (Y - mean[None]).astype(np.float32) if keep_draws else None
    Y += rng.standard_normal(Y.shape) * noise_sd[:, :, None]
    qs = sorted({q for lv in LEVELS for q in (0.5 - lv / 200.0, 0.5 + lv / 200.0)} | {0.5})
    Q = np.quantile(Y, qs, axis=0)
    qi = {q: i for i, q in enumerate(qs)}
    bands = {lv: (Q[qi[0.5 - lv / 200.0]], Q[qi[0.5 + lv / 200.0]]) for lv in LEVELS}
    measured = model.measured
    hot, cold = (model.channels.index(c) for c in model.rig.layout.face)
    tavg = 0.5 * (measured[hot] + measured[cold])
    starts = np.concatenate([[model.time[0]], model.step_time])
    since = model.time - starts[model.sample_hold]
    return Prediction(
        source=str(exp.path),
        label=draws.label,
        laws=draws.laws,
        time=model.time.copy(),
        channels=model.channels,
        measured=measured,
        mean=mean,
        median=Q[qi[0.5]],
        bands=bands,
        tavg=tavg,
        current=np.asarray(exp.current, float),
        n_draws=len(Y),
        seconds=_time.perf_counter() - t0,
        since_step=since,
        deviations=dev,
        noise_sd=noise_sd if keep_draws else None,
        noise_tau=noise_tau if keep_draws else None,
        n_failed=n_failed,
        start_current=model.start_current,
        predictive=Y.astype(np.float32) if keep_predictive else None,
        face=model.rig.layout.face,
        labels={**{c: model.rig.layout.describe(c) for c in model.sensor_channels}, "voltage_V": "voltage"},
    )


@dataclass(frozen=True)
class PredictResult:
    """Result of :func:`predict`.

    Attributes
    ----------
    linear : Prediction
        The calibration's laws (linear in T-bar).
    constant : Prediction or None
        R and S constant at :data:`CONSTANT_AT_C`, anchored on its own.
    draws : PredictiveDraws
        The linear-law draws that were simulated.
    seed : int
    seconds : float
    """

    linear: Prediction
    constant: Prediction | None
    draws: PredictiveDraws
    seed: int
    seconds: float

    def to_json(self):
        """``metrics.json`` (docs/outputs.md, 'metrics.json (predict)'): the metrics plus the context."""
        doc = {"channels": self.linear.metrics()}
        doc.update(
            {
                "module": self.linear.label,
                "experiment": self.linear.source,
                "laws": "linear",
                "n_draws": self.linear.n_draws,
                "seed": self.seed,
                "levels_percent": list(LEVELS),
                "units": {c: "K (= degC difference)" if c.endswith("_C") else "V" for c in self.linear.channels},
                "rmse_about": "the posterior-predictive mean",
                "by_Tavg": self.linear.by_tavg(),
                "anchor": self.draws.anchor,
                "n_failed_draws": self.linear.n_failed,
                # the run's initial state: the steady state of this current, fitted on its first minute
                "initial_state": {
                    "pre_history_current_A": self.linear.start_current,
                    "first_level_A": float(self.linear.current[0]),
                },
                "seconds": self.seconds,
            }
        )
        if self.constant is not None:
            doc["constant_laws"] = {
                "T_C": CONSTANT_AT_C,
                "channels": self.constant.metrics(),
                "by_Tavg": self.constant.by_tavg(),
            }
        return doc


def predict(
    run, experiment, module, batch, *, n_draws=500, seed=0, compare_constant=True, keep_predictive=False, progress=None
):
    """Posterior-predictive bands of an experiment for a module or a new unit.

    Parameters
    ----------
    run : CalibrationRun
    experiment : tembayes.data.Experiment
    module : str
        A module id of the run, or ``"population"``.
    batch : tembayes.data.Batch
        The calibrated batch (the identification runs anchor the rig).
    n_draws : int
        Predictive draws.
    seed : int
    compare_constant : bool
        Also predict with R and S constant at 35 degC.
    keep_predictive : bool
        Keep every draw of the (linear-law) predictive, noise included
        (:attr:`Prediction.predictive`: memory ``n_draws x 5 x samples x 4`` bytes),
        for :func:`~tembayes.predict.inference.to_inference_data`.
    progress : callable, optional

    Returns
    -------
    PredictResult
    """
    t0 = _time.perf_counter()
    say = progress or (lambda msg: None)
    if n_draws < 10:
        raise TembayesError(f"n_draws must be at least 10 (bands from fewer draws are noise), got {n_draws}")
    if module != "population" and module not in run.module_ids:
        raise DataError(
            run.path / "posterior.nc",
            f"has no module '{module}'",
            f"Choose one of {list(run.module_ids)} or 'population'.",
        )
    rig = run.rig_for(batch)
    model = RunModel(experiment, rig, start="data")
    ids = list(run.module_ids) if module == "population" else [module]
    results = {}
    for laws in ("linear", "constant") if compare_constant else ("linear",):
        per = {}
        for mid in ids:
            say(f"{mid}: anchoring the rig on the identification run ({laws} laws)")
            per[mid] = module_draws(run, mid, batch.modules[mid].identification, rig, laws=laws)
        if laws == "linear":
            lin = per
        rng = stream(seed, f"{module}/{laws}")
        if module == "population":
            draws = population_draws(run, per, rng, n_draws)
            params = draws.params
            if laws == "constant":
                # the population's laws frozen; K moved as the modules' own rig fits moved it
                params = constant_laws(params)
                ratio = np.mean(
                    [np.mean(per[m].params["K_W_per_K"]) / np.mean(lin[m].params["K_W_per_K"]) for m in ids]
                )
                params["K_W_per_K"] = params["K_W_per_K"] * ratio
            draws = PredictiveDraws(params, draws.noise_sd, "population", laws, draws.anchor, draws.noise_tau)
        else:
            draws = subsample(per[module], rng, n_draws)
        say(f"{module}: simulating {n_draws} predictive draws of {Path(str(experiment.path)).name} ({laws} laws)")
        keep = keep_predictive and laws == "linear"
        results[laws] = (simulate_predictive(model, draws, rng, progress=progress, keep_predictive=keep), draws)
    return PredictResult(
        linear=results["linear"][0],
        constant=results.get("constant", (None,))[0],
        draws=results["linear"][1],
        seed=int(seed),
        seconds=_time.perf_counter() - t0,
    )
