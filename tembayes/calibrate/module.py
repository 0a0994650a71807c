"""Calibrate one module: its posterior from the identification run.

The pipeline, each step a plain function of the previous one's result:

1. :func:`~tembayes.calibrate.stepdata.step_data` cuts the run into step
   windows;
2. :func:`fit_map` finds the posterior mode with the exact step-response
   model (Levenberg-Marquardt, batched finite-difference Jacobians) and its
   Laplace covariance;
3. the exact model is expanded around the mode
   (:class:`~tembayes.calibrate.model.LinearisedModel`) -- the posterior is
   ~0.1 % wide, where the response is linear to far below the noise;
4. a short pilot run of emcee on that expansion finds the posterior's centre
   and width, the expansion is rebuilt there, and emcee samples the full
   posterior (laws, K, rig nuisances, step shift, noise) on it until
   converged (:func:`~tembayes.calibrate.sampler.sample`), half its moves
   independence proposals from a Student-t fitted to the pilot; the hold
   currents' measurement errors are integrated out of the likelihood
   (:class:`~tembayes.calibrate.likelihood.LevelErrors`);
5. the expansion is *checked* against the exact model on posterior draws by
   Pareto-smoothed importance sampling: ``k_hat`` < 0.7 means the exact
   posterior is what was sampled (to importance-sampling accuracy); above
   that, on 400 draws and again on 2000 for a converged run
   (:func:`_final_checks`), the expansion is rebuilt at the posterior mean
   and the sampling repeated.

A module's random streams come from the run seed and the module id, so a
module's result does not depend on which other modules are in the batch or
on the order they run in.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from tembayes.calibrate import sampler as smp
from tembayes.calibrate.adequacy import adequacy_numbers, assess
from tembayes.calibrate.diagnostics import PSIS_K_MAX, ModuleDiagnostics, PsisCheck
from tembayes.calibrate.discrepancy import held_nuisance_spread, held_parameters, window_sandwich
from tembayes.calibrate.likelihood import OFFSET_SD, LevelErrors, StepLikelihood, noise_priors
from tembayes.calibrate.model import SHIFT, LinearisedModel, StepResponseModel
from tembayes.calibrate.modelform import DEFAULT_FORM, get_form
from tembayes.calibrate.parameters import ParameterSpace
from tembayes.calibrate.priors import LawPrior, ParameterPrior, effect_priors, module_law_priors, rig_prior
from tembayes.calibrate.stepdata import step_data
from tembayes.common.arvizlib import az
from tembayes.common.draws import even_indices
from tembayes.common.heap import keep_short_lived_blocks_on_the_heap
from tembayes.common.lstsq import design_covariance
from tembayes.common.seeds import spawned, stream
from tembayes.constants import KELVIN, MODULE_PARAMETERS, T_REF
from tembayes.data.write import atomic_write_text
from tembayes.errors import ModelError
from tembayes.physics.effects import EFFECT_PARAMETERS
from tembayes.physics.rigread import rig_from_config

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from scipy.optimize import OptimizeResult

    from tembayes.calibrate.stepdata import StepData
    from tembayes.data import Datasheet, Experiment, LazyModule, Module
    from tembayes.physics.rig import RigDescription

#: Resolution of the calibration model: legs in 4 cells, every block cell of
#: the rig file in 3 (the reference rig's blocks in 6).  The
#: paper-sized model (lumped module, 2 cells per block) misses the first
#: minute after a step by up to 0.1 K in dT (heat takes ~25 s through a
#: block, the legs' Joule heat is released along them), which biases K and S
#: by percents; 4 x 6 is within the sensor noise of a 14 x 8 model.
LEG_CELLS = 4
BLOCK_SPLIT = 3

#: How a calibration widens its laws for a model that is not the rig (``CalibrationOptions.discrepancy``).
DISCREPANCIES = ("none", "window-sandwich", "robust")
#: An expansion whose PSIS k_hat on the first ``psis_probe`` steps of a
#: rebuildable stage exceeds this is rebuilt at once (k_hat > 1: importance
#: weights without a finite mean -- the expansion is not the posterior, and
#: sampling it to convergence only to reject it cost misspecified modules
#: three full budgets, 25-80 min).  Stages that pass go on unchanged.
EARLY_REBUILD_K = 1.0
#: Expansion steps in posterior sds.  A parabola through 0 and +-h misses a
#: cubic term by ``t (d^3 - d h^2)``; its mean square under d ~ N(0, 1) is
#: ``15 - 6 h^2 + h^4``, least at h = sqrt(3) (40 % below h = 1).  Measured
#: on a bench module: log-weight sd 0.52 -> 0.23, PSIS k 0.53 -> 0.35, so the
#: first expansion usually passes and the second sampling run is saved.
EXPANSION_STEP_SD = 3.0**0.5
#: Relative cost change at which the mode search stops.  The mode is only the
#: first expansion's centre (the pilot recentres it on the posterior), and on
#: the example modules a change of 1e-4 of the cost is ~0.2 log-likelihood
#: units, inside the posterior; scipy's 1e-8 spent a third of the search's
#: simulations (rejected trial steps) on the last 1e-5 of it.
MODE_FTOL = 1e-4


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of a module calibration.

    Attributes
    ----------
    leg_cells, block_split : int
        Resolution of the calibration model: the module's legs in
        ``leg_cells`` cells, every block cell of the rig in ``block_split``
        (odd).
    nwalkers : int or None
        emcee walkers (>= 2 x parameters); None: 2 x parameters + 2.
    max_steps : int
        Sampler budget per module [steps].
    thin_by : int
        Steps per stored iteration (checkpoint interval).
    pilot : int
        Steps of the pilot run that recentres the expansion on the posterior
        (the mode found with white noise is not its centre once the noise
        and the window offsets are inferred).
    keep : int
        Draws kept per walker in ``posterior.nc``.
    psis_draws : int
        Posterior draws checked against the exact model.
    psis_recheck_draws : int
        Draws of a second look when a converged stage's first check fails
        (0: none; both looks are kept in the diagnostics' ``psis``).
        ``k_hat`` from 400 draws rests on their 60 largest weights and
        scatters by ~0.17 (0.11 from 2000; weights ``exp(c x^2)``, 40 samples
        each): on one liquid-plate module the same stage's weights gave 0.70
        from 400 draws and 0.49 from 2000.  A converged stage is rebuilt only
        when the larger sample, whose ``k_hat`` the 0.7 threshold is meant for
        (Vehtari et al. 2024: ``1 - 1/log10(S)`` = 0.697 at 2000 draws), also
        fails (:attr:`~tembayes.calibrate.diagnostics.PsisCheck.passes`); an
        unconverged one is rebuilt anyway.
    max_relinearise : int
        Last expansion stage (the pilot is stage 0); reported, not fatal.
    psis_probe : int
        Steps after which a rebuildable stage checks its expansion (PSIS)
        once, and is cut and rebuilt if ``k_hat`` > :data:`EARLY_REBUILD_K`
        (0: never; the last stage never is).
    model : str
        The model's physics, ``"paper"`` or ``"full"``
        (:mod:`tembayes.calibrate.modelform`).
    effects : tuple of str
        Catalogue effects added to the model, their sizes sampled under their
        priors (``tembayes calibrate --effect NAME``).
    effect_values : dict
        Effect parameters added to the model at a fixed value
        (``--effect NAME=VALUE``; name -> value, SI).
    discrepancy : str
        ``"none"``; ``"window-sandwich"``: the laws' posterior widened to
        the scatter of the step windows' scores; ``"robust"``: that, and the
        uncertainty of the rig parameters held fixed carried over
        (:mod:`tembayes.calibrate.discrepancy`).
    law_prior : LawPrior or None
        The laws' prior: None, the datasheet's; a known type's population
        for a new unit of it (``tembayes calibrate --unit-prior RUN``,
        :func:`tembayes.calibrate.earlier.unit_prior_of_run`).
    stage_steps : int
        Budget of a sampling run whose expansion may still be rebuilt (the
        run is cut there and the expansion rebuilt from its walkers).
        Default: the whole budget -- with differential evolution alone the
        laws' autocorrelation times are 200-350 steps, R-hat <= 1.01 needs
        ~100 of them, and cutting a run whose expansion passed the PSIS check
        only threw its steps away (measured: 45 000 steps in three runs
        instead of one).  A lower value suits module types whose first
        expansion mixes badly.
    """

    leg_cells: int = LEG_CELLS
    block_split: int = BLOCK_SPLIT
    nwalkers: int | None = None
    max_steps: int = 60000
    thin_by: int = 10
    pilot: int = 3000
    keep: int = 100
    psis_draws: int = 400
    psis_recheck_draws: int = 2000
    max_relinearise: int = 3
    stage_steps: int = 60000
    psis_probe: int = 4000
    model: str = DEFAULT_FORM
    effects: tuple = ()
    effect_values: dict = field(default_factory=dict)
    discrepancy: str = "robust"
    law_prior: LawPrior | None = None

    def to_json(self) -> dict:
        """The options as ``summary.json`` and the module files record them."""
        return {**self.__dict__, "law_prior": None if self.law_prior is None else self.law_prior.to_json()}

    @classmethod
    def from_json(cls, doc: Mapping) -> CalibrationOptions:
        """The options a run recorded (:meth:`to_json`); keys this version does not know are ignored."""
        known = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in doc.items() if k in known}
        if kw.get("law_prior") is not None:
            kw["law_prior"] = LawPrior.from_json(kw["law_prior"])
        if "effects" in kw:
            kw["effects"] = tuple(kw["effects"])  # JSON made it a list
        return cls(**kw)

    def __post_init__(self):
        if self.discrepancy not in DISCREPANCIES:
            raise ModelError(f"discrepancy must be one of {DISCREPANCIES}, got {self.discrepancy!r}")
        form = get_form(self.model)
        named = set(self.effects) | {EFFECT_PARAMETERS.get(k) for k in self.effect_values}
        if None in named:
            bad = [k for k in self.effect_values if k not in EFFECT_PARAMETERS]
            raise ModelError(f"unknown effect parameter(s) {bad}")
        inside = sorted(named & set(form.includes))
        if inside:
            raise ModelError(
                f"the '{form.name}' model already contains {', '.join(inside)}; add it only to a "
                "--model paper calibration"
            )
        both = sorted(set(self.effects) & {EFFECT_PARAMETERS[k] for k in self.effect_values})
        if both:
            raise ModelError(f"effect {', '.join(both)} given both sampled and at a fixed value")


@dataclass(frozen=True)
class ModuleCalibration:
    """The posterior of one module (a plain result object; plots read it).

    Attributes
    ----------
    module_id : str
    names : tuple of str
        Sampled parameters, coordinate order.
    draws : dict
        ``name -> ndarray (nwalkers, keep)`` posterior draws in SI: the
        sampled ``names`` and the ``held`` ones.
    log_prob : ndarray, shape (nwalkers, keep)
    step_loglike : ndarray, shape (nwalkers, keep, n_steps)
        Log-likelihood of every step window at every kept draw.
    priors : dict
        ``name -> ParameterPrior.to_dict()``.
    map : dict
        Posterior mode (SI).
    diagnostics : ModuleDiagnostics
        How the sampling went (:mod:`tembayes.calibrate.diagnostics`).
    steps : dict
        Per step: ``t_s``, ``dI_A``, ``direction``, ``Tavg_K`` (model's junction
        mean at the step, at the mode).
    observed : dict
        ``time_s``, ``step``, ``since_s``, ``obs`` (3, n), ``noise`` (3,).
    hysteresis : dict
        Up- minus down-step differences of R and S with their sd.
    seed : dict
        The module's seeds.
    rig : str
        Calibration rig name.
    options : dict
        The calibration's options (:meth:`CalibrationOptions.to_json`).
    held : tuple of str
        Rig parameters the calibration held whose range ``--discrepancy
        robust`` carried over: their draws are the values each draw's laws
        were moved for (:meth:`~tembayes.calibrate.discrepancy.HeldSpread.values`).
    units : dict
        ``name -> unit`` (SI) of the calibration rig's parameters among
        ``names`` and ``held``, as its rig file gives them (``posterior.nc``'s
        ``units`` attributes).
    """

    module_id: str
    names: tuple
    draws: dict
    log_prob: np.ndarray
    step_loglike: np.ndarray
    priors: dict
    map: dict
    diagnostics: ModuleDiagnostics
    steps: dict
    observed: dict
    hysteresis: dict
    seed: dict
    rig: str
    options: dict = field(default_factory=dict)
    held: tuple = ()
    units: dict = field(default_factory=dict)

    def law_draws(self) -> np.ndarray:
        """``(n, 5)`` draws of the module parameters (contract order, SI)."""
        return np.column_stack([self.draws[k].ravel() for k in MODULE_PARAMETERS])


def module_seed(seed: int, module_id: str) -> tuple[int, np.random.Generator]:
    """Seeds of a module derived from the run seed and the module id.

    Returns
    -------
    (int, numpy.random.Generator)
        emcee's seed and a Generator for everything else.
    """
    a, b = spawned(seed, str(module_id)).generate_state(2)
    return int(a), np.random.default_rng(int(b))


#: Largest share of a module face's heat a conductance may carry and still be
#: sampled as a shunt (in its log, :func:`~tembayes.calibrate.priors.rig_prior`).
SHUNT_SHARE = 0.2


def positive_coordinates(space: ParameterSpace) -> list[int]:
    """Coordinates the robust carry-over moves relatively, so they stay positive: the resistances."""
    return [j for j, pr in enumerate(space.priors) if pr.kind == "reciprocal"]


def flat_coordinates(space: ParameterSpace, rig: RigDescription) -> dict[int, tuple[float, float]]:
    """The flat priors' coordinates and ranges (lead shares, own response times): the carry-over keeps them inside.

    A share sampled as itself sits near its floor; moved additively it crossed zero in a few
    draws, and moved relatively past one (reference-faces, where a sensor's depth and its lead
    share move its reading alike), which ``predict`` (reading a share through its logit) cannot
    read.  The posterior has no mass outside the share's flat prior, so the moved draws stay in it.
    """
    return {
        j: (pr.center - pr.scale, pr.center + pr.scale)
        for j, pr in enumerate(space.priors)
        if pr.name in rig.lead_parameters | rig.lag_parameters
    }


def calibration_rig(rig_config: Mapping | None, options: CalibrationOptions) -> RigDescription:
    """The calibration model's rig for a batch's ``[rig]`` table and the options' resolution and form."""
    form = get_form(options.model)
    return rig_from_config(
        rig_config or {},
        leg_cells=options.leg_cells,
        block_split=options.block_split,
        layers=form.layers,
        physics={**form.physics, **dict(options.effect_values)},
    )


def parameter_space(
    rig: RigDescription,
    datasheet: Datasheet,
    data: StepData,
    shift_bound: float,
    effects: Sequence[str] = (),
    form: str = DEFAULT_FORM,
    law_prior: LawPrior | None = None,
) -> tuple[ParameterSpace, ParameterSpace]:
    """The sampled coordinates of a module.

    Laws and K (under ``law_prior``, default the datasheet's), rig
    nuisances, the model form's sampled physics, the parameters of
    ``effects`` (catalogue names added to the model), step shift, noise.

    Raises
    ------
    ModelError
        An effect the form already contains.
    """
    form = get_form(form)
    inside = [e for e in effects if e in form.includes]
    if inside:
        raise ModelError(
            f"the '{form.name}' model already contains {', '.join(inside)}; add it only to a --model paper calibration"
        )
    nuis = [p for p in rig.parameters if p.high / p.low > form.min_range and not p.held]
    fixed = {p.name: p.nominal for p in rig.parameters if p not in nuis}
    # a rig whose every sensor has its own response time leaves the form's common one nothing to act on
    own_lags = bool(rig.sensors) and set(rig.lags) == set(rig.sensors)
    pri = (
        list(module_law_priors(datasheet, law_prior))
        + [
            rig_prior(
                p,
                linear=p.name in rig.lead_parameters | rig.lag_parameters,
                shunt=p.unit == "W/K" and rig.face_heat_share(p.name) < SHUNT_SHARE,
            )
            for p in nuis
        ]
        + [p for p in form.priors if not (own_lags and p.name == "sensor_tau_s")]
        + list(effect_priors(effects))
    )
    pri.append(ParameterPrior(SHIFT, "uniform", 0.0, shift_bound))
    model_space = ParameterSpace(tuple(pri), fixed)
    return model_space, ParameterSpace(tuple(pri) + noise_priors(data), fixed)


def _prior_residuals(space, X):
    cols = []
    for j, p in enumerate(space.priors):
        if p.kind == "uniform":
            continue
        if p.kind == "reciprocal":
            with np.errstate(divide="ignore", invalid="ignore"):
                cols.append((np.log(X[:, j]) - np.log(p.coordinate_center)) / p.scale)
        else:
            cols.append((X[:, j] - p.coordinate_center) / p.scale)
    return np.column_stack(cols)


def _prior_sd(space):
    """Prior sd of every coordinate (a uniform's half-width / sqrt 3)."""
    return np.array([p.coordinate_sd for p in space.priors])


def fd_steps(space: ParameterSpace) -> np.ndarray:
    """Finite-difference steps per coordinate (~0.1-1 % of a prior width)."""
    h = []
    for p in space.priors:
        if p.kind in ("lognormal", "logitnormal"):
            h.append(1e-3)
        elif p.kind == "reciprocal":
            h.append(1e-3 * p.coordinate_center)
        elif p.kind == "uniform":
            h.append(0.02 * p.scale)
        else:
            h.append(1e-3 * p.scale)
    return np.array(h)


def fit_map(
    model: StepResponseModel,
    space: ParameterSpace,
    data: StepData,
    x0: np.ndarray,
    *,
    max_nfev: int = 60,
    ftol: float = 1e-8,
) -> tuple[np.ndarray, np.ndarray, OptimizeResult]:
    """Posterior mode of the model coordinates, and its Laplace covariance.

    The noise is white at the measured level.  ``ftol`` is the optimiser's
    relative cost change at which it stops (``scipy.optimize.least_squares``).

    Returns
    -------
    (ndarray, ndarray, OptimizeResult)
        Mode ``(p,)``, covariance ``(p, p)``, the optimiser's result.
    """
    h = fd_steps(space)
    noise = data.noise[None, :, None]

    def resid(X):
        Y = model.predict(space.params(X), strict=False)
        r = ((data.obs[None] - Y) / noise).reshape(len(X), -1)
        # a trial point whose simulation fails (the optimiser probing far
        # out) gets a large finite misfit, so the trust region shrinks
        r[~np.all(np.isfinite(r), axis=1)] = 1e3
        return np.hstack([r, _prior_residuals(space, X)])

    def jac(x):
        X = np.repeat(x[None], 2 * len(x), axis=0)
        for j in range(len(x)):
            X[2 * j, j] += h[j]
            X[2 * j + 1, j] -= h[j]
        X = space.clip(X)
        R = resid(X)
        dx = X[0::2, :][np.arange(len(x)), np.arange(len(x))] - X[1::2, :][np.arange(len(x)), np.arange(len(x))]
        return ((R[0::2] - R[1::2]) / dx[:, None]).T

    lo = np.full(len(x0), -np.inf)
    hi = np.full(len(x0), np.inf)
    scale = np.ones(len(x0))
    for j, p in enumerate(space.priors):
        if p.kind == "uniform":
            lo[j], hi[j] = p.center - 0.98 * p.scale, p.center + 0.98 * p.scale
            scale[j] = 0.5 * p.scale
        elif p.kind in ("lognormal", "logitnormal"):
            scale[j] = 0.01
        elif p.kind == "reciprocal":
            lo[j] = p.coordinate_floor
            scale[j] = 0.01 * p.coordinate_center
        else:
            scale[j] = 0.1 * p.scale
    x0 = np.clip(x0, lo + 1e-12, hi - 1e-12)
    sol = least_squares(
        lambda x: resid(x[None])[0],
        x0,
        jac=jac,
        bounds=(lo, hi),
        x_scale=scale,
        method="trf",
        max_nfev=max_nfev,
        ftol=ftol,
    )
    cov = design_covariance(sol.jac)
    return sol.x, cov, sol


@dataclass(frozen=True)
class LaplaceFit:
    """A run's posterior mode and Laplace covariance (:func:`laplace_fit`), with the problem it was found on.

    Attributes
    ----------
    data : StepData
    model : StepResponseModel
    space : ParameterSpace
        The sampled coordinates without the noise.
    x : ndarray, shape (p,)
        The mode.
    cov : ndarray, shape (p, p)
        Its :func:`laplace_covariance`.
    jac : ndarray
        The whitened residuals' Jacobian at the mode (data rows, then prior rows).
    residuals : ndarray, shape (nc, n)
        The whitened data residuals at the mode.
    nfev : int
    converged : bool
        The mode search stopped on a tolerance, not on its budget.
    """

    data: object
    model: StepResponseModel
    space: ParameterSpace
    x: np.ndarray
    cov: np.ndarray
    jac: np.ndarray
    residuals: np.ndarray
    nfev: int
    converged: bool


def calibration_problem(experiment, datasheet, rig_config, opt, effects=()):
    """``(rig, step data, model, model space, space)`` of a calibration of ``experiment``.

    ``effects`` are catalogue effects added to the model form, besides ``opt.effects``.
    """
    rig = calibration_rig(rig_config, opt)
    data = step_data(experiment, face=rig.layout.face)
    model = StepResponseModel(data, rig)
    named = tuple(dict.fromkeys((*effects, *opt.effects)))  # the run's own and the gap's candidate
    model_space, space = parameter_space(rig, datasheet, data, model.shift_bound, named, opt.model, opt.law_prior)
    return rig, data, model, model_space, space


def laplace_fit(
    experiment, datasheet, *, rig_config=None, options=None, effects=(), start=None, max_nfev=60, held=None
):
    """The calibration's problem on ``experiment``, its mode from ``start`` (:func:`start_point`), and the Laplace covariance.

    ``effects`` are catalogue effects added to the model form (and
    ``options.effects``); ``held`` (``name -> value``, SI) takes sampled
    parameters out of the search at those values.
    """
    opt = options or CalibrationOptions()
    _, data, model, space, _ = calibration_problem(experiment, datasheet, rig_config, opt, effects)
    if held:
        unknown = sorted(set(held) - set(space.names) - set(space.fixed))
        if unknown:
            raise ValueError(f"laplace_fit: held parameters {unknown} are not in the model's parameter space")
        space = ParameterSpace(tuple(p for p in space.priors if p.name not in held), {**space.fixed, **held})
    with threadpool_limits(limits=1, user_api="blas"):
        x, _, sol = fit_map(model, space, data, start_point(space, start), max_nfev=max_nfev)
        r = (data.obs - model.predict(space.params(x[None]), strict=False)[0]) / data.noise[:, None]
    return LaplaceFit(
        data, model, space, x, laplace_covariance(sol.jac, space), sol.jac, r, int(sol.nfev), bool(sol.status > 0)
    )


def laplace_covariance(jac: np.ndarray, space: ParameterSpace) -> np.ndarray:
    """The Laplace covariance at a mode of :func:`fit_map` from its whitened Jacobian (data and prior rows).

    The Gauss-Newton Hessian of the data and prior terms; a uniform prior
    counts with its own variance, so a coordinate the data leave open has
    its prior's width instead of an infinite one.
    """
    H = jac.T @ jac
    for j, p in enumerate(space.priors):
        if p.kind == "uniform":
            H[j, j] += 3.0 / p.scale**2
    cov = np.linalg.inv(H)
    return 0.5 * (cov + cov.T)


def start_point(space: ParameterSpace, start: Mapping[str, float] | None = None) -> np.ndarray:
    """Coordinates where a mode search starts.

    The prior centres, the step shift at the middle of its interval, every
    effect at zero (the base model), overridden by ``start`` (``name ->
    value``, SI; names not in ``space`` ignored).
    """
    x0 = np.array([pr.to_unconstrained(pr.center) for pr in space.priors])
    x0[space.index(SHIFT)] = 0.0
    for name in EFFECT_PARAMETERS:
        if name in space.names:
            x0[space.index(name)] = 0.0
    for name, value in (start or {}).items():
        if name in space.names:
            x0[space.index(name)] = space.priors[space.index(name)].to_unconstrained(value)
    return x0


def _initial_walkers(rng, space, model_space, x_map, cov, data, nw):
    """Walkers from the Laplace approximation (model) and near-prior noise."""
    p = model_space.ndim
    Z = rng.multivariate_normal(np.zeros(p), cov, size=nw, method="eigh")
    X = np.empty((nw, space.ndim))
    X[:, :p] = x_map + Z
    for j in range(p, space.ndim):
        name = space.names[j]
        if name in OFFSET_SD:
            c = OFFSET_SD.index(name)
            X[:, j] = np.log(0.2 * data.noise[c]) + 0.5 * rng.standard_normal(nw)
        else:
            X[:, j] = 0.05 * rng.standard_normal(nw)
    return space.clip(X)


def psis_check(
    like_exact: StepLikelihood,
    like_lin: StepLikelihood,
    X: np.ndarray,
    rng: np.random.Generator,
    n: int,
    *,
    stage: int,
    early_steps: int | None = None,
) -> PsisCheck:
    """Pareto-k of the importance weights exact/linearised on ``n`` of the posterior draws ``X``.

    Parameters
    ----------
    like_exact, like_lin : StepLikelihood
        The exact model's likelihood and the expansion's.
    X : ndarray, shape (S, p)
        Posterior draws in the sampler's coordinates (the five laws first).
    rng : numpy.random.Generator
        Picks the ``n`` draws (without replacement; all of them if fewer).
    n : int
    stage : int
        The expansion stage checked.
    early_steps : int, optional
        Steps after which a check during sampling ran.

    Returns
    -------
    PsisCheck
    """
    idx = rng.choice(len(X), size=min(n, len(X)), replace=False)
    Xs = X[idx]
    lw = like_exact.log_likelihood_x(Xs) - like_lin.log_likelihood_x(Xs)
    slw, k = az.psislw(lw - lw.max())
    w = np.exp(lw - lw.max())
    ess = float(w.sum() ** 2 / np.sum(w * w))
    return PsisCheck(
        stage=stage,
        k_hat=float(k),
        weight_ess_fraction=ess / len(Xs),
        max_logw_dev=float(np.max(np.abs(lw - np.median(lw)))),
        early_steps=early_steps,
        draws=len(Xs),
        law_shift_sd=law_shift_sd(Xs[:, : len(MODULE_PARAMETERS)], slw),
    )


def law_shift_sd(laws: np.ndarray, log_weights: np.ndarray) -> float:
    """Largest shift of the weighted over the plain mean of the laws, in their plain sds.

    Parameters
    ----------
    laws : ndarray, shape (S, 5)
        The laws' draws in the sampler's coordinates (the log of R0, S0 and K;
        a shift in sds is the same in the values to first order).
    log_weights : ndarray, shape (S,)

    Returns
    -------
    float
    """
    w = np.exp(log_weights - np.max(log_weights))
    w = w / w.sum()
    sd = laws.std(axis=0)
    shift = np.abs(w @ laws - laws.mean(axis=0)) / np.where(sd > 0, sd, np.inf)
    return float(np.max(shift))


def hysteresis(
    lin: LinearisedModel,
    like: StepLikelihood,
    x_mean: np.ndarray,
    data: StepData,
    space: ParameterSpace,
    level_response: np.ndarray | None = None,
) -> dict:
    """Up- minus down-step difference of R and S (GLS on the expansion).

    The model gets two extra terms: R and S raised by ``h/2`` in the windows
    after up-steps and lowered by ``h/2`` after down-steps (their effect taken from
    the expansion's R0 and S0 columns, window by window).  Fitted with
    the other coordinates free at the posterior mean's noise, and the hold
    currents' errors (``level_response``, ``(nh, 3, n)``) as further
    columns under their ``N(0, level_sd^2)`` prior.

    Returns
    -------
    dict
        ``R_ohm`` and ``S_V_per_K``: ``{"estimate", "sd", "z"}`` of up - down.
    """
    mi = like._mi
    J = lin.J  # (p, 3, n)
    sgn = data.direction[data.step].astype(float)
    iR, iS = space.index("R0_ohm"), space.index("S0_V_per_K")
    R0 = float(np.exp(x_mean[iR]))
    S0 = float(np.exp(x_mean[iS]))
    # columns in units of ohm and V/K (J's R0/S0 columns are per log unit)
    hR = 0.5 * sgn[None, :] * J[mi.index(iR)] / R0
    hS = 0.5 * sgn[None, :] * J[mi.index(iS)] / S0
    A = np.concatenate([J, hR[None], hS[None]], axis=0).reshape(J.shape[0] + 2, -1).T
    sigma, beta = like._noise(x_mean[None])
    r = (data.obs - lin.predict(x_mean[mi][None])[0]).ravel()
    # whiten by the noise only (the window offsets are second order here)
    w = np.repeat(1.0 / sigma[0], data.obs.shape[1])
    Aw = A * w[:, None]
    rw = r * w
    if level_response is not None:
        nh = len(data.level_sd)
        Gw = level_response.reshape(nh, -1).T * w[:, None]
        Aw = np.vstack([np.hstack([Aw, Gw]), np.hstack([np.zeros((nh, A.shape[1])), np.diag(1.0 / data.level_sd)])])
        rw = np.concatenate([rw, np.zeros(nh)])
    coef, *_ = np.linalg.lstsq(Aw, rw, rcond=None)
    cov = design_covariance(Aw)
    out = {}
    k0 = A.shape[1]
    for name, k in (("R_ohm", k0 - 2), ("S_V_per_K", k0 - 1)):
        est, sd = float(coef[k]), float(np.sqrt(cov[k, k]))
        out[name] = {"estimate": est, "sd": sd, "z": est / sd if sd > 0 else float("nan")}
    return out


def calibrate_module(module: Module | LazyModule, datasheet: Datasheet, **kw) -> ModuleCalibration:
    """Posterior of one module's parameters from its identification run.

    Parameters
    ----------
    module : tembayes.data.Module
    datasheet : tembayes.data.Datasheet
        Scales the priors.
    rig_config : dict, optional
        The batch's ``[rig]`` table.
    seed : int
        Run seed; the module's streams derive from it and the module id.
    options : CalibrationOptions, optional
    checkpoint : str or Path, optional
        Checkpoint file prefix (``.json`` state, ``.stage<n>.<k>.npz`` sampler chunks).
    resume : bool
        Continue from the checkpoint if there is one.
    progress : callable, optional
        ``progress(message)`` for stage messages.
    progress_bar : bool
        Show the sampler's progress bar.
    effects : sequence of str
        Catalogue effects added to the base model, their parameters sampled
        under :func:`~tembayes.calibrate.priors.effect_priors` (the gap
        diagnosis's recalibration).  Default none: the paper's model.
    start : dict, optional
        ``name -> value`` (SI) where the search for the mode starts (e.g. the
        base calibration's posterior mean); default the prior centres, the
        effects at zero.

    Returns
    -------
    ModuleCalibration
    """
    keep_short_lived_blocks_on_the_heap()
    # one BLAS thread throughout: OpenBLAS picks other kernels (other
    # rounding) with more threads, and the same seed must give the same bits
    with threadpool_limits(limits=1, user_api="blas"):
        return _calibrate_module(module, datasheet, **kw)


def _read_state(path):
    """A module's resume state, or None (set aside as ``*.damaged``, with a warning) if it cannot be read."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as exc:
        os.replace(path, path + ".damaged")
        warnings.warn(
            f"resume state {path} cannot be read ({exc}); renamed {os.path.basename(path)}.damaged, the "
            "module starts again from its posterior mode",
            RuntimeWarning,
            stacklevel=3,
        )
        return None


@dataclass(frozen=True)
class _Problem:
    """One module's calibration problem: its step data, the model, the sampled space and the likelihood pieces."""

    module_id: str
    experiment: Experiment
    rig_config: dict
    data: object
    rig: object
    model: StepResponseModel
    model_space: ParameterSpace
    space: ParameterSpace
    nwalkers: int
    options: CalibrationOptions
    base_seed: int
    emcee_seed: int


def _problem(module, datasheet, rig_config, opt, effects, seed) -> _Problem:
    emcee_seed, rng = module_seed(seed, module.id)
    experiment = module.identification
    rig, data, model, model_space, space = calibration_problem(experiment, datasheet, rig_config, opt, effects)
    nwalkers = 2 * space.ndim + 2 if opt.nwalkers is None else int(opt.nwalkers)
    if nwalkers < 2 * space.ndim:
        raise ModelError(f"nwalkers must be at least 2 x {space.ndim} parameters, got {nwalkers}")
    return _Problem(
        module.id,
        experiment,
        dict(rig_config or {}),
        data,
        rig,
        model,
        model_space,
        space,
        nwalkers,
        opt,
        base_seed=int(rng.integers(2**63)),
        emcee_seed=emcee_seed,
    )


def step_method_laws(experiment: Experiment, rig_config: Mapping | None) -> dict[str, float]:
    """R0, R1, S0 and S1 of the step method at the rig's nominal values, or ``{}`` when it cannot give them.

    R from the voltage jumps, S from the hold ends
    (:func:`~tembayes.identify.pipeline.step_estimates`): within a few % of
    the posterior, where the datasheet is ~20 % off, so the mode search
    starts near its end (on the example's TEM2: 18 s instead of 37 s).
    A run or rig the step method cannot read leaves the search at the prior
    centre.
    """
    from tembayes.identify.pipeline import step_estimates

    try:
        e = step_estimates(experiment, rig_from_config(rig_config or {}))
    except (ModelError, ValueError, np.linalg.LinAlgError):
        return {}
    okR, okS = np.isfinite(e["R_ohm"]), np.isfinite(e["S_V_per_K"])
    if okR.sum() < 3 or okS.sum() < 3:
        return {}
    R1, R0 = np.polyfit(e["Tavg_R_C"][okR] + KELVIN - T_REF, e["R_ohm"][okR], 1)
    S1, S0 = np.polyfit(e["Tavg_S_C"][okS] + KELVIN - T_REF, e["S_V_per_K"][okS], 1)
    if not (R0 > 0 and S0 > 0):
        return {}
    return {"R0_ohm": float(R0), "R1_ohm_per_K": float(R1), "S0_V_per_K": float(S0), "S1_V_per_K2": float(S1)}


def _coordinates(space: ParameterSpace) -> dict[str, str]:
    """What each sampled coordinate is (its prior's kind): a resume must read stored vectors the same way."""
    return {p.name: p.kind for p in space.priors}


def _start_state(prob, state_file, resume, start, say) -> dict:
    """The resume state, or a new one at the posterior mode (written to ``state_file``)."""
    if resume and state_file and os.path.exists(state_file):
        state = _read_state(state_file)
        if state is not None and state.get("coordinates") == _coordinates(prob.space):
            return state
        if state is not None:
            # another version's coordinates (e.g. log g where this one samples 1/g): its vectors mean other values
            for stage in range(prob.options.max_relinearise + 1):
                smp.ChunkCheckpoint(f"{state_file[: -len('.json')]}.stage{stage}").clear()
            warnings.warn(
                f"{prob.module_id}: the resume state {state_file} was written by a version of tembayes that samples "
                "other coordinates; the module starts again from its posterior mode",
                RuntimeWarning,
                stacklevel=3,
            )
    say(f"{prob.module_id}: posterior mode")
    start = {**step_method_laws(prob.experiment, prob.rig_config), **(start or {})}
    x0 = start_point(prob.model_space, {k: v for k, v in start.items() if k != SHIFT})
    x_map, cov, sol = fit_map(prob.model, prob.model_space, prob.data, x0, ftol=MODE_FTOL)
    state = {
        "coordinates": _coordinates(prob.space),
        "x_map": x_map.tolist(),
        "cov": cov.tolist(),
        "x_lin": x_map.tolist(),
        "x_level": x_map.tolist(),
        "stage": 0,
        "map_nfev": int(sol.nfev),
    }
    if state_file:
        atomic_write_text(state_file, json.dumps(state))
    return state


@dataclass
class _Stage:
    """One sampling run on one expansion of the model."""

    run: smp.SamplerRun
    lin: LinearisedModel
    like: StepLikelihood
    rng: np.random.Generator
    early: PsisCheck | None
    budget: int


def _run_stage(prob, state, levels, exact_like, *, checkpoint, resume, progress_bar, say) -> _Stage:
    """Sample the posterior on the expansion at ``state["x_lin"]`` (stage ``state["stage"]``)."""
    opt, space, stage = prob.options, prob.space, state["stage"]
    pilot, last = stage == 0, stage >= opt.max_relinearise
    # steps of sqrt(3) posterior sds: the expansion interpolates over the posterior
    h = np.maximum(EXPANSION_STEP_SD * np.sqrt(np.diag(np.array(state["cov"]))), fd_steps(prob.model_space))
    # never probe beyond two prior sds: a coordinate the data leave open (an
    # effect traded against a rig parameter) would send the expansion
    # where the rig cannot be simulated
    h = np.minimum(h, 2.0 * _prior_sd(prob.model_space))
    lin = LinearisedModel(prob.model, prob.model_space, np.array(state["x_lin"]), h, noise=prob.data.noise)
    like = StepLikelihood(prob.data, lin, space, levels)
    # a stream per stage: a resumed run draws exactly what a straight one does
    rng = stream(prob.base_seed, stage)
    p0 = _initial_walkers(
        rng, space, prob.model_space, np.array(state["x_map"]), np.array(state["cov"]), prob.data, prob.nwalkers
    )
    if state.get("walkers") is not None:
        p0 = space.clip(np.array(state["walkers"]))
    say(f"{prob.module_id}: {'pilot' if pilot else 'sampling'} (expansion {stage})")
    budget = opt.pilot if pilot else (opt.max_steps if last else min(opt.max_steps, opt.stage_steps))
    early = []

    def probe(post, steps):
        """One PSIS check of a rebuildable stage's expansion, at the first check past psis_probe steps."""
        if early or steps < opt.psis_probe:
            return False
        # its own stream: the stage's draws stay those of a run without the probe
        check = psis_check(
            exact_like,
            like,
            post.reshape(-1, space.ndim),
            stream(prob.base_seed, stage, 1),
            opt.psis_draws,
            stage=stage,
            early_steps=steps,
        )
        early.append(check)
        return check.k_hat > EARLY_REBUILD_K

    prop = state.get("proposal")
    with warnings.catch_warnings():
        # only the final run's convergence is reported (by the caller)
        warnings.simplefilter("ignore", RuntimeWarning)
        run = smp.sample(
            like.log_prob,
            p0,
            seed=prob.emcee_seed + stage,
            monitor=range(len(MODULE_PARAMETERS)),
            checkpoint=None if checkpoint is None else f"{checkpoint}.stage{stage}",
            resume=resume,
            thin_by=opt.thin_by,
            max_steps=budget,
            progress=progress_bar,
            label=prob.module_id + (" pilot" if pilot else ""),
            proposal=None if prop is None else (np.array(prop["mean"]), np.array(prop["cov"])),
            stop=None if pilot or last or opt.psis_probe <= 0 else probe,
            min_stored=opt.keep,
        )
    return _Stage(run, lin, like, rng, early[0] if early else None, budget)


def _next_state(state, run, psis, p) -> dict:
    """The state of the next stage: the expansion recentred on this run's posterior, its walkers as the start."""
    half = run.chain[len(run.chain) // 2 :].reshape(-1, run.chain.shape[-1])
    x_map = half[:, :p].mean(axis=0)
    # the next run also proposes independently from this one's posterior
    proposal = {"mean": half.mean(axis=0).tolist(), "cov": np.cov(half.T).tolist()}
    return {
        **state,
        "x_lin": x_map.tolist(),
        "stage": state["stage"] + 1,
        "x_map": x_map.tolist(),
        "cov": np.cov(half[:, :p].T).tolist(),
        "walkers": run.chain[-1].tolist(),
        "psis": [c.to_json() for c in psis],
        "proposal": proposal,
    }


def _final_checks(prob, st, stage, exact_like) -> list[PsisCheck]:
    """A finished stage's PSIS checks, the last deciding: ``psis_draws``, then ``psis_recheck_draws`` where that fails.

    The first look decides every stage it passes (with the same random
    numbers as a run without a second look); one that fails a converged run
    is followed by a second look on ``psis_recheck_draws`` draws of the same
    chain (drawn anew from their own stream, so they may include the first
    look's), and that look decides
    (:attr:`~tembayes.calibrate.diagnostics.PsisCheck.passes`: it also needs
    usable weights, since on a liquid-plate module it reached ``k_hat`` 0.69
    with 12 effective draws of 2000).
    """
    opt, X = prob.options, st.run.chain.reshape(-1, prob.space.ndim)
    first = psis_check(exact_like, st.like, X, st.rng, opt.psis_draws, stage=stage)
    if first.k_hat < PSIS_K_MAX or not st.run.converged or opt.psis_recheck_draws <= opt.psis_draws:
        return [first]
    second = psis_check(exact_like, st.like, X, stream(prob.base_seed, stage, 2), opt.psis_recheck_draws, stage=stage)
    return [first, dataclasses.replace(second, recheck=True)]


def _sample_stages(prob, state, levels, exact_like, *, state_file, timings, say, **stage_kw):
    """Pilot, then sampling runs until one converges on an expansion PSIS accepts (or the last stage).

    Returns
    -------
    (_Stage, list of PsisCheck, bool, dict)
        The last run, every expansion check, whether any run resumed from a
        checkpoint, and the last stage's state (its ``x_map`` is the centre
        the run started from).
    """
    psis = [PsisCheck(**c) for c in state.get("psis", [])]
    resumed = False
    while True:
        t0 = time.perf_counter()
        stage = state["stage"]
        st = _run_stage(prob, state, levels, exact_like, say=say, **stage_kw)
        timings[f"sample_s_{stage}"] = time.perf_counter() - t0
        resumed = resumed or st.run.resumed
        if st.early is not None and st.early.k_hat > EARLY_REBUILD_K:
            psis.append(st.early)
            say(
                f"{prob.module_id}: expansion off after {st.early.early_steps} steps "
                f"(k_hat {st.early.k_hat:.2f}); rebuilding it at the posterior mean"
            )
        elif stage > 0:
            psis += _final_checks(prob, st, stage, exact_like)
            if (psis[-1].passes and st.run.converged) or stage >= prob.options.max_relinearise:
                return st, psis, resumed, state
            last = psis[-1]
            off = f"expansion off (k_hat {last.k_hat:.2f} on {last.draws} draws, {last.effective_draws:.0f} effective)"
            why = f"not converged in {st.budget} steps" if last.passes else off
            say(f"{prob.module_id}: {why}; rebuilding the expansion at the posterior mean")
        state = _next_state(state, st.run, psis, prob.model_space.ndim)
        if state_file:
            atomic_write_text(state_file, json.dumps(state))


def _calibrate_module(
    module,
    datasheet,
    *,
    rig_config=None,
    seed=0,
    options=None,
    checkpoint=None,
    resume=False,
    progress=None,
    progress_bar=False,
    effects=(),
    start=None,
):
    opt = options or CalibrationOptions()
    say = progress or (lambda msg: None)
    t_start = time.perf_counter()
    prob = _problem(module, datasheet, rig_config, opt, effects, seed)
    state_file = None if checkpoint is None else f"{checkpoint}.json"
    state = _start_state(prob, state_file, resume, start, say)
    timings = {"map_s": time.perf_counter() - t_start}
    # the hold currents' errors: their effect on the channels, once, at the
    # mode (linear in the ~0.02 mA errors; the posterior is ~0.1 % wide)
    G = prob.model.level_jacobian(prob.model_space.params(np.array(state.get("x_level", state["x_map"]))[None]))
    levels = LevelErrors(G, prob.data.level_sd, prob.data.window_starts, prob.data.noise)
    exact_like = StepLikelihood(prob.data, prob.model, prob.space, levels)
    st, psis, resumed, state = _sample_stages(
        prob,
        state,
        levels,
        exact_like,
        state_file=state_file,
        timings=timings,
        say=say,
        checkpoint=checkpoint,
        resume=resume,
        progress_bar=progress_bar,
    )
    post = _posterior(prob, st, levels)
    diag = _diagnostics(st.run, prob.space.names, psis, resumed, state.get("map_nfev"), levels, timings, post)
    if not diag.converged:
        warnings.warn(
            f"{module.id}: not converged (sampler converged: {st.run.converged} after {st.run.steps} steps, R-hat "
            f"max {np.nanmax(st.run.rhat):.3f}, bulk ESS min {np.nanmin(st.run.ess_bulk):.0f}; {'; '.join(diag.reasons())}); "
            "results are marked converged: false",
            RuntimeWarning,
            stacklevel=3,
        )
    timings["total_s"] = time.perf_counter() - t_start
    data = prob.data
    x_centre = np.array(state["x_map"])
    return ModuleCalibration(
        module_id=module.id,
        names=prob.space.names,
        held=post.held,
        draws=post.draws,
        log_prob=st.run.log_prob[post.sel].T.copy(),
        step_loglike=post.step_loglike,
        priors={pr.name: pr.to_dict() for pr in prob.space.priors},
        map=_mode_values(prob.model_space, x_centre),
        diagnostics=diag,
        steps={
            "t_s": data.step_time,
            "dI_A": data.dI,
            "direction": data.direction,
            "Tavg_K": _step_tavg(prob, x_centre),
        },
        observed={"time_s": data.time, "step": data.step, "since_s": data.since, "obs": data.obs, "noise": data.noise},
        hysteresis=hysteresis(
            st.lin, st.like, st.run.chain.reshape(-1, prob.space.ndim).mean(axis=0), data, prob.space, G
        ),
        seed={"run": int(seed), "emcee": prob.emcee_seed},
        rig=prob.rig.name,
        options=opt.to_json(),
        units={q.name: q.unit for q in prob.rig.parameters if q.name in prob.space.names + post.held},
    )


@dataclass(frozen=True)
class _Posterior:
    """The kept draws, widened by the discrepancy model, and what the fit's adequacy checks found."""

    draws: dict
    step_loglike: np.ndarray
    sel: np.ndarray
    discrepancy: dict
    adequacy: dict
    held: tuple = ()


def _posterior(prob, st, levels) -> _Posterior:
    """Keep ``keep`` draws per walker, check the fit's adequacy, widen the laws by the discrepancy model."""
    opt, space, p = prob.options, prob.space, prob.model_space.ndim
    run = st.run
    sel = even_indices(run.chain.shape[0], opt.keep)
    kept = run.chain[sel].transpose(1, 0, 2)  # (nw, keep, p)
    nw, nk = kept.shape[:2]
    flat = kept.reshape(-1, space.ndim)
    step_ll = st.like.pointwise(flat)
    laws = [space.names.index(k) for k in MODULE_PARAMETERS]
    scatter = window_sandwich(flat, step_ll, laws)  # always: how far the windows disagree
    fitted = st.lin.predict(flat[:, :p].mean(axis=0)[None])[0]
    adequacy = assess(
        adequacy_numbers(scatter, space.values(flat), prob.data, prob.data.obs - fitted, MODULE_PARAMETERS)
    )
    discrepancy = {"method": "none"}
    held_draws = {}
    if opt.discrepancy in ("window-sandwich", "robust"):
        centre = flat[:, laws].mean(axis=0)
        flat = flat.copy()
        flat[:, laws] = centre + (flat[:, laws] - centre) @ scatter.stretch.T
        discrepancy = {**scatter.to_json(MODULE_PARAMETERS), "method": opt.discrepancy}
    if opt.discrepancy == "robust":
        law_sd = flat[:, laws].std(axis=0)
        held = held_parameters(prob.rig, prob.model_space)
        spread = held_nuisance_spread(
            prob.model, prob.model_space, flat[:, :p].mean(axis=0), st.lin.J, prob.data.noise, held
        )
        xi = spread.draw(st.rng, len(flat))
        flat = spread.apply(flat, xi, relative=positive_coordinates(space), shares=flat_coordinates(space, prob.rig))
        held_draws = spread.values(xi)
        discrepancy["held_sd_over_posterior_sd"] = spread.to_json(space.names, laws, law_sd)
        if spread.not_carried:
            discrepancy["held_not_carried"] = list(spread.not_carried)
            warnings.warn(
                f"{prob.module_id}: the exact model cannot be simulated at the posterior's centre, so the range of "
                f"{', '.join(spread.not_carried)} is not carried over to the laws; the posterior lies where only "
                "the model's expansion reaches (see the expansion check, psis_k)",
                RuntimeWarning,
                stacklevel=4,
            )
    if opt.discrepancy != "none":
        step_ll = st.like.pointwise(flat)
    draws = {k: v.reshape(nw, nk) for k, v in {**space.values(flat), **held_draws}.items()}
    return _Posterior(draws, step_ll.reshape(nw, nk, -1), sel, discrepancy, adequacy.to_json(), tuple(held_draws))


def _diagnostics(run, names, psis, resumed, map_nfev, levels, timings, post) -> ModuleDiagnostics:
    """The sampling record of the final run, with the posterior's discrepancy and adequacy records."""
    n_laws = len(MODULE_PARAMETERS)
    return ModuleDiagnostics(
        rhat=dict(zip(names, map(float, run.rhat))),
        ess_bulk=dict(zip(names, map(float, run.ess_bulk))),
        ess_tail=dict(zip(names, map(float, run.ess_tail))),
        tau_steps=dict(zip(names, map(float, run.tau))),
        rhat_max=float(np.max(run.rhat[:n_laws])),
        rhat_walkers_max=float(np.max(run.rhat_walkers[:n_laws])),
        ess_bulk_min=float(np.min(run.ess_bulk[:n_laws])),
        tau_max_steps=float(np.max(run.tau[:n_laws])),
        tau_max_all_steps=float(np.max(run.tau)),
        chain_over_tau=float(run.chain.shape[0] * run.thin_by / np.max(run.tau[:n_laws])),
        steps=run.steps,
        burn_in_steps=run.burn * run.thin_by,
        nwalkers=run.chain.shape[1],
        acceptance_mean=float(np.mean(run.acceptance)),
        acceptance_min=float(np.min(run.acceptance)),
        sampler_converged=bool(run.converged),
        psis=tuple(psis),
        resumed=bool(resumed),
        map_nfev=map_nfev,
        # largest response to a hold level outside the two windows kept, in
        # noise sds per level sd (the tridiagonal approximation's neglect)
        level_band_neglected=levels.neglected,
        discrepancy=post.discrepancy,
        adequacy=post.adequacy,
        timings=timings,
    )


def _mode_values(model_space, x):
    """``name -> value`` (SI) of the model coordinates ``x``."""
    return dict(zip(model_space.names, (float(v[0]) for v in model_space.values(x[None]).values())))


def _step_tavg(prob, x):
    """The junction mean temperature [K] at every step (exact model at ``x``)."""
    data = prob.data
    sim = prob.model.simulate(prob.model_space.params(x[None]))
    tavg = 0.5 * (sim["t_hot"][0] + sim["t_cold"][0])
    return np.array(
        [
            tavg[np.flatnonzero(data.step == k)[np.argmin(np.abs(data.since[data.step == k]))]]
            for k in range(data.n_steps)
        ]
    )


def sample_prior_only(
    module: Module | LazyModule,
    datasheet: Datasheet,
    *,
    rig_config: Mapping | None = None,
    seed: int = 0,
    options: CalibrationOptions | None = None,
) -> tuple[dict[str, np.ndarray], ParameterSpace, smp.SamplerRun]:
    """Negative control: the same sampler on the prior alone (no likelihood).

    Everything but the data is the calibration's own path (parameter space,
    coordinates and their Jacobians, initial walkers, emcee, convergence
    rules), so draws that do not reproduce the prior point at a bug there.

    Returns
    -------
    (dict, ParameterSpace, SamplerRun)
        ``name -> ndarray`` of draws (SI), the space (its priors), the run.
    """
    opt = options or CalibrationOptions()
    emcee_seed, rng = module_seed(seed, module.id)
    rig = calibration_rig(rig_config, opt)
    data = step_data(module.identification, face=rig.layout.face)
    model = StepResponseModel(data, rig)
    _, space = parameter_space(rig, datasheet, data, model.shift_bound, form=opt.model, law_prior=opt.law_prior)
    nwalkers = 2 * space.ndim + 2 if opt.nwalkers is None else int(opt.nwalkers)
    p0 = space.sample_prior(rng, nwalkers)
    run = smp.sample(
        space.log_prior, p0, seed=emcee_seed, monitor=range(space.ndim), thin_by=opt.thin_by, max_steps=opt.max_steps
    )
    return space.values(run.chain.reshape(-1, space.ndim)), space, run
