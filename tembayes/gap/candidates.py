"""The diagnosis's worker jobs: a model refitted, or recalibrated, and scored on the held-out data.

- :func:`refit_job`: the identification run refitted with the base model or
  one catalogue effect added (:func:`~tembayes.gap.which.refit`) and, for the
  screen, its Laplace posterior's predictive of the held-out runs;
- :func:`candidate_job`: a module recalibrated with an effect added (the
  sampler, :func:`~tembayes.calibrate.module.calibrate_module`) and its
  posterior's predictive of the held-out runs.

Both run in worker processes (:mod:`~tembayes.gap.jobs`): they are top-level
functions of picklable arguments, and a model that fails comes back as a
result with ``failed`` set (the reason), not as an exception.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from tembayes.common.seeds import stream
from tembayes.gap.conflicts import range_conflicts
from tembayes.gap.evidence import evaluate_run
from tembayes.physics import effects as E
from tembayes.predict.predictive import posterior_draws
from tembayes.predict.runmodel import RunModel

#: Laplace draws per predictive draw of a screen refit (the anchoring keeps fewer).
LAPLACE_DRAWS_PER_DRAW = 4


@dataclass
class RefitOutcome:
    """A refit job's result.

    Attributes
    ----------
    module, effect : str, str or None
        The module and the effect added (None: the base model).
    seconds : float
        Wall time of the job [s].
    refit : Refit or None
    evals : list of RunEvaluation or None
        The Laplace posterior's held-out runs (without their gap maps), when asked for.
    conflicts : list of str or None
        The rig parameters that posterior puts outside their range, when asked for.
    failed : str or None
        Why the model failed.
    """

    module: str
    effect: str | None
    seconds: float = 0.0
    refit: object = None
    evals: list | None = None
    conflicts: list | None = None
    failed: str | None = None


@dataclass
class Recalibration:
    """A candidate job's result: one module recalibrated with an effect.

    Attributes
    ----------
    module, effect : str
    seconds : float
        Wall time of the job [s].
    failed : str or None
        Why the model failed (the rest is then empty).
    converged : bool
        The sampler's verdict.
    warnings : list of str
        The recalibration's runtime warnings, for the parent to raise.
    evals : list of RunEvaluation or None
        Its held-out runs (without their gap maps).
    size : dict or None
        The effect's parameters: ``name -> {"median", "q05", "q95", "unit"}`` (SI).
    refit : Refit or None
        The mode search from the posterior median (its identification windows).
    conflicts : list of str or None
        The rig parameters outside their range.
    calibration : ModuleCalibration or None
    """

    module: str
    effect: str
    seconds: float
    failed: str | None = None
    converged: bool = False
    warnings: list = field(default_factory=list)
    evals: list | None = None
    size: dict | None = None
    refit: object = None
    conflicts: list | None = None
    calibration: object = None


def score_posterior(module, raw, priors, rig, *, tag, seed, n_draws, alpha):
    """A posterior anchored on the identification run and scored on the held-out runs.

    Parameters
    ----------
    module : ModuleData
    raw : dict
        ``name -> (M,)`` posterior draws (SI).
    priors : dict
        Their priors.
    rig : RigDescription
    tag : str
        The model, for its draws' seed stream (every model compared on a run
        shares the run's own stream).
    seed : int
    n_draws : int
        Predictive draws per held-out run.
    alpha : float
        Level of each gap-map cell test.

    Returns
    -------
    draws : PredictiveDraws
        Anchored.
    evals : list of RunEvaluation
        One per held-out run, without its gap map.
    conflicting : list of str
        The rig parameters outside their range.
    """
    draws = posterior_draws(raw, priors, module.id, module.identification, rig)
    evals = [
        evaluate_run(
            RunModel(exp, rig, start="data"),
            draws,
            stream(seed, module.id, tag, exp.path),
            stream(seed, module.id, exp.path),
            n_draws=n_draws,
            alpha=alpha,
        )
        for exp in module.validations
    ]
    for e in evals:
        e.gap_map = None  # not needed back in the parent
    return draws, evals, [r["parameter"] for r in range_conflicts(raw, rig) if r["conflict"]]


@dataclass(frozen=True)
class Setting:
    """What every job of one diagnosis shares (picklable: it goes to the workers).

    Attributes
    ----------
    datasheet : Datasheet
    rig_config : dict or None
        The batch's rig configuration.
    base : CalibrationOptions
        The run's options (the refits').
    options : CalibrationOptions
        The recalibrations' options.
    seed : int
    n_draws : int
        Predictive draws per held-out run of a recalibration.
    screen_draws : int
        Predictive draws per held-out run of a screen refit (its Laplace posterior).
    alpha : float
        Level of each gap-map cell test.
    """

    datasheet: object
    rig_config: object
    base: object
    options: object
    seed: int
    n_draws: int
    screen_draws: int
    alpha: float

    def refit(self, module, effect, start, window_noise, held=None):
        """:func:`~tembayes.gap.which.refit` of ``module``'s identification run with the run's options."""
        from tembayes.gap.which import refit

        return refit(
            module,
            self.datasheet,
            effect,
            rig_config=self.rig_config,
            start=start,
            options=self.base,
            window_noise=window_noise,
            held=held,
        )


def refit_job(setting, module, effect, start, heldout, window_noise=None, held=None):
    """One refit and, with ``heldout``, its Laplace posterior scored on the held-out runs (a worker's job).

    Parameters
    ----------
    setting : Setting
    module : ModuleData
    effect : str or None
        The effect added (None: the base model).
    start : dict
        Where the mode search starts (SI).
    heldout : bool
    window_noise : WindowNoise, optional
        The base calibration's noise model, by which the held-out windows are judged.
    held : dict, optional
        Rig parameters held at a value (SI): a range check.

    Returns
    -------
    RefitOutcome
    """
    from threadpoolctl import threadpool_limits

    from tembayes.calibrate.module import calibration_rig
    from tembayes.errors import TembayesError

    s, t0 = setting, time.perf_counter()
    out = RefitOutcome(module=module.id, effect=effect)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a wrong effect's refit may probe where the rig strains
        try:
            out.refit = s.refit(module, effect, start, window_noise, held)
            if heldout:
                n = s.screen_draws
                raw = out.refit.draws(stream(s.seed, module.id, "laplace", effect), LAPLACE_DRAWS_PER_DRAW * n)
                rig = calibration_rig(s.rig_config, s.base)
                with threadpool_limits(limits=1, user_api="blas"):
                    _, out.evals, out.conflicts = score_posterior(
                        module,
                        raw,
                        out.refit.priors,
                        rig,
                        tag=f"screen:{effect}",
                        seed=s.seed,
                        n_draws=n,
                        alpha=s.alpha,
                    )
        except TembayesError as err:
            out.failed = str(err)
    out.seconds = time.perf_counter() - t0
    return out


def candidate_job(setting, module, effect, start, refitted, window_noise=None):
    """One module recalibrated with ``effect`` and scored on its held-out runs (a worker's job).

    A recalibration whose model fails (the effect drives the rig somewhere it
    cannot be simulated) is a candidate that does not help: it comes back
    with ``failed`` and the reason.

    Parameters
    ----------
    setting : Setting
    module : ModuleData
    effect : str
    start : dict
        Where the refit starts (SI).
    refitted : Refit or None
        The screen's refit with ``effect``, if there is one.
    window_noise : WindowNoise, optional
        The base calibration's noise model: the yardstick of every model's held-out windows in one
        diagnosis (a candidate's own noise parameters may have absorbed what it does not explain).

    Returns
    -------
    Recalibration
    """
    from threadpoolctl import threadpool_limits

    from tembayes.calibrate.module import calibration_rig
    from tembayes.errors import TembayesError

    s, t0 = setting, time.perf_counter()
    rig = calibration_rig(s.rig_config, s.base)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            cal, raw, rf = _recalibrate(s, module, effect, start, refitted, window_noise)
            with threadpool_limits(limits=1, user_api="blas"):
                draws, evals, conflicting = score_posterior(
                    module, raw, cal.priors, rig, tag=effect, seed=s.seed, n_draws=s.n_draws, alpha=s.alpha
                )
        except TembayesError as err:
            return Recalibration(module=module.id, effect=effect, failed=str(err), seconds=time.perf_counter() - t0)
    return Recalibration(
        module=module.id,
        effect=effect,
        seconds=time.perf_counter() - t0,
        converged=bool(cal.diagnostics.converged),
        warnings=[str(w.message) for w in caught],
        evals=evals,
        size=effect_size(effect, draws),
        refit=rf,
        conflicts=conflicting,
        calibration=cal,
    )


def _recalibrate(setting, module, effect, start, refitted, window_noise):
    """The sampler with ``effect`` added, from the refit's mode; ``(calibration, raw draws, refit)``.

    The refit returned is the mode search again from the posterior median:
    the identification windows are judged at the recalibration's own fit (a
    screen refit may have stopped short of the mode), by ``window_noise``.
    """
    from tembayes.calibrate.module import calibrate_module

    s = setting
    rf = refitted or s.refit(module, effect, start, window_noise)
    cal = calibrate_module(
        module,
        s.datasheet,
        rig_config=s.rig_config,
        seed=s.seed,
        options=s.options,
        effects=(effect,),
        start={**start, **rf.mode()},
    )
    raw = {k: np.asarray(v).ravel() for k, v in cal.draws.items()}
    median = {k: float(np.median(v)) for k, v in raw.items()}
    return cal, raw, s.refit(module, effect, median, window_noise)


def effect_size(effect, draws):
    """An effect's parameters in anchored draws (where the step likelihood left them open, the anchoring's).

    Parameters
    ----------
    effect : str
    draws : PredictiveDraws
        Anchored.

    Returns
    -------
    dict
        ``name -> {"median", "q05", "q95", "unit"}`` (SI).
    """
    size = {}
    for p in E.get(effect).parameters:
        x = np.asarray(draws.params[p.name], float)
        size[p.name] = {
            "median": float(np.median(x)),
            "q05": float(np.quantile(x, 0.05)),
            "q95": float(np.quantile(x, 0.95)),
            "unit": p.unit,
        }
    return size
