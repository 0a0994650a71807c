"""The paper's deterministic rig fit and its validation (Figures 8 and 9).

"The model parameters, e.g. the resistances and thermal capacitances, are
optimized using a nonlinear data-based optimization procedure, seeded with
initial values based on first principles": least squares of the rig's
thermal parameters and the module conductance K on the identification run,
with the R and S laws held fixed, against the four block sensors.
Parameters are fitted in log space (positive), seeded at the rig
description's nominal values, with a weak prior that keeps them near the
documented range: each parameter's log is penalised as a Gaussian whose
+-2 sd span that range.  The four sensor temperatures alone cannot tell a
paste conductance from a plate capacitance well; without the prior the fit
wanders to the bounds.  The Jacobian comes from one batched simulation of all
finite-difference perturbations at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from tembayes.constants import KELVIN, LAW_PARAMETERS, T_REF
from tembayes.physics.rigread import REFERENCE
from tembayes.physics.simulate import Inputs, simulate

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from tembayes.data.experiment import Experiment
    from tembayes.physics.rig import RigDescription

#: A rig parameter whose documented range spans more than this ratio (high / low) is fitted by default.
FIT_RANGE_RATIO = 1.2


def fit_parameters(rig: RigDescription) -> tuple[str, ...]:
    """What the rig fit adjusts by default: ``K_W_per_K`` and the rig's loosely known parameters.

    Those whose range spans more than :data:`FIT_RANGE_RATIO`, not held, not
    shares, not the module's own ``c_legs`` (it sits with K); the rest stays
    nominal (on the reference rig: the steel's geometry and heat capacity are
    known to a few per cent, the depths of T1 and T4 held; the seats of T2 and
    T3, which the step transients tell, are fitted).
    """
    return ("K_W_per_K",) + tuple(
        p.name
        for p in rig.parameters
        if not p.held and not p.is_share and p.name != "c_legs" and p.high > FIT_RANGE_RATIO * p.low
    )


SENSOR_NOISE_K = 0.004  # reference rig NTC noise [K]
VOLTAGE_NOISE_V = 0.001  # reference rig voltage noise [V]


@dataclass(frozen=True)
class RigFit:
    """Result of :func:`fit_rig`.

    Attributes
    ----------
    values : dict
        Fitted parameters (SI).
    sd : dict
        Their standard errors from the Gauss-Newton covariance, scaled by the
        residual variance (SI).
    rmse : dict
        RMSE per sensor channel [K] (and ``voltage_V`` [V]) on the fitted run.
    success : bool
    nfev : int
    message : str
    """

    values: dict
    sd: dict
    rmse: dict
    success: bool
    nfev: int
    message: str


def decimate(inputs: Inputs, max_rate: float = 1.0) -> np.ndarray:
    """Indices of samples at no more than ``max_rate`` [Hz] (always keeps the last)."""
    dt = float(np.median(np.diff(inputs.time)))
    step = max(1, int(round(1.0 / (max_rate * dt))))
    idx = np.arange(0, len(inputs.time), step)
    if idx[-1] != len(inputs.time) - 1:
        idx = np.append(idx, len(inputs.time) - 1)
    return idx


def fit_rig(
    exp: Experiment,
    laws: Mapping[str, float],
    *,
    rig: RigDescription = REFERENCE,
    parameters: Sequence[str] | None = None,
    K0: float | None = None,
    max_rate: float = 1.0,
    fixed: Mapping[str, float] | None = None,
    prior: bool = True,
    voltage: bool = True,
) -> RigFit:
    """Least-squares fit of the rig's thermal parameters with the laws fixed.

    Two stages.  Stage 1 is a plain fit with the sensors' noise as scale.
    Its residuals are mostly *model* error (the lumped model against a
    distributed world): smooth, autocorrelated and larger than the noise.  So
    each channel's residual RMS ``s_c`` and lag-1 autocorrelation ``rho_c``
    set its weight in stage 2: residuals scaled by ``s_c`` and by the
    effective sample size ``N (1 - rho) / (1 + rho)``, which puts the data and
    the prior on a comparable footing.  Stage 2 starts again from the seed.

    Parameters
    ----------
    exp : tembayes.data.Experiment
        The identification run.
    laws : dict
        ``R0_ohm``, ``R1_ohm_per_K``, ``S0_V_per_K``, ``S1_V_per_K2`` (SI).
    rig : RigDescription
    parameters : sequence of str, optional
        What to fit: ``K_W_per_K`` and rig parameter names; default
        :func:`fit_parameters`.
    K0 : float, optional
        Starting module conductance [W/K] (e.g. the datasheet's).
    max_rate : float
        The run is simulated at no more than this rate [Hz] (holds last
        minutes; the sensors' slowest dynamics are well resolved at 1 Hz).
    fixed : dict, optional
        Other parameters held at given values.
    prior : bool
        Penalise departures from the documented ranges (see the module
        docstring); ``K`` gets a +-50 % (2 sd) range about ``K0``.
    voltage : bool
        Fit the terminal voltage too: it carries the junction temperature
        difference, which the block sensors see only through paste and steel.

    Returns
    -------
    RigFit
    """
    parameters = fit_parameters(rig) if parameters is None else tuple(parameters)
    whole = Inputs.from_experiment(exp, rig)
    idx = decimate(whole, max_rate)
    inputs = Inputs(whole.time[idx], whole.current[idx], whole.boundaries[:, idx])
    sensors = [exp.channel(c)[idx] for c in rig.sensors]
    meas = np.vstack(sensors + ([exp.voltage[idx]] if voltage else []))
    nch = meas.shape[0]
    nominal = rig.nominal()
    x0, psd = [], []
    for p in parameters:
        if p == "K_W_per_K":
            x0.append(K0 if K0 is not None else 0.5)
            psd.append(np.log(1.5) / 2.0)
        else:
            x0.append(nominal[p])
            rp = rig.parameter(p)
            psd.append(np.log(rp.high / rp.low) / 4.0)
    x0 = np.log(np.array(x0, dtype=float))
    psd = np.array(psd)
    base = {k: float(v) for k, v in laws.items() if k in LAW_PARAMETERS} | dict(fixed or {})

    def model(X):
        params = dict(base)
        for j, p in enumerate(parameters):
            params[p] = np.exp(X[:, j])
        for k in LAW_PARAMETERS:
            params[k] = np.full(len(X), base[k])
        sim = simulate(inputs, params, rig=rig)
        return np.concatenate([sim.sensors, sim.voltage[:, None]], axis=1)[:, :nch] - meas[None]

    def solve(weights, use_prior):
        h = 1e-4  # step in log space

        def residuals(X):
            r = (model(X) * weights[None, :, None]).reshape(len(X), -1)
            if use_prior:
                r = np.concatenate([r, (X - x0[None]) / psd[None]], axis=1)
            return r

        last = {}

        def fun(x):
            R = residuals(np.vstack([x, x + h * np.eye(len(x))]))
            last["x"], last["J"] = x.copy(), ((R[1:] - R[0][None]) / h).T
            return R[0]

        def jac(x):
            if "x" in last and np.array_equal(last["x"], x):
                return last["J"]
            fun(x)
            return last["J"]

        return least_squares(
            fun,
            x0,
            jac=jac,
            bounds=(x0 - np.log(20.0), x0 + np.log(20.0)),
            method="trf",
            x_scale="jac",
            xtol=1e-8,
            ftol=1e-10,
            max_nfev=200,
        )

    noise = np.r_[np.full(len(sensors), SENSOR_NOISE_K), VOLTAGE_NOISE_V][:nch]
    res1 = solve(1.0 / noise, False)
    r1 = model(res1.x[None])[0]
    scale = np.sqrt(np.mean(r1**2, axis=1))
    rho = np.array([np.corrcoef(rc[:-1], rc[1:])[0, 1] for rc in r1])
    rho = np.clip(np.nan_to_num(rho), 0.0, 0.999)
    n_factor = (1 - rho) / (1 + rho)
    weights = np.sqrt(n_factor) / np.maximum(scale, noise)
    res = solve(weights, prior) if prior else res1
    J = res.jac
    dof = max(len(res.fun) - len(x0), 1)
    s2 = max(1.0, float(res.fun @ res.fun) / dof)
    try:
        sd_log = np.sqrt(np.clip(np.diag(np.linalg.inv(J.T @ J) * s2), 0, None))
    except np.linalg.LinAlgError:
        sd_log = np.full(len(x0), np.nan)
    values = {p: float(np.exp(v)) for p, v in zip(parameters, res.x)}
    sd = {p: float(np.exp(v) * s) for p, v, s in zip(parameters, res.x, sd_log)}
    r = model(res.x[None])[0]
    rmse = {ch: float(np.sqrt(np.mean(rr**2))) for ch, rr in zip(list(rig.sensors) + ["voltage_V"], r)}
    return RigFit(values, sd, rmse, bool(res.success), int(res.nfev), str(res.message))


def constant_laws(laws: Mapping[str, float], T_C: float = 35.0) -> dict[str, float]:
    """The laws frozen at their value at ``T_C`` [degC] (the paper's Figure 8 model)."""
    x = T_C + KELVIN - T_REF
    return {
        "R0_ohm": laws["R0_ohm"] + laws["R1_ohm_per_K"] * x,
        "R1_ohm_per_K": 0.0,
        "S0_V_per_K": laws["S0_V_per_K"] + laws["S1_V_per_K2"] * x,
        "S1_V_per_K2": 0.0,
    }


def validation_errors(
    exp: Experiment, laws: Mapping[str, float], rig_values: Mapping[str, float], *, rig: RigDescription = REFERENCE
) -> dict:
    """Simulate a run with fixed parameters; errors per sensor and on the voltage.

    Returns
    -------
    dict
        Channel -> ``{"rmse": ..., "max_abs": ...}`` (K for sensors, V for
        ``voltage_V``), plus ``"simulation"`` (the :class:`Simulation`).
    """
    params = {k: laws[k] for k in LAW_PARAMETERS} | dict(rig_values)
    sim = simulate(Inputs.from_experiment(exp, rig), params, rig=rig)
    out = {}
    for c, ch in enumerate(sim.channels):
        r = exp.channel(ch) - sim.sensors[0, c]
        out[ch] = {"rmse": float(np.sqrt(np.mean(r**2))), "max_abs": float(np.max(np.abs(r)))}
    rv = exp.voltage - sim.voltage[0]
    out["voltage_V"] = {"rmse": float(np.sqrt(np.mean(rv**2))), "max_abs": float(np.max(np.abs(rv)))}
    out["simulation"] = sim
    return out
