"""Expected posterior widths of an identification run, before it is made.

The laws' posterior sd a calibration reaches on a run is, to first order,
that of its Laplace approximation: the step-response likelihood's
Gauss-Newton information at the mode, plus the datasheet's and the rig's
priors, with the rig nuisances and the step phase sampled alongside the laws.
:func:`expected_widths` computes it on one run of a module -- a bench
simulation of the protocol to be designed -- exactly as the calibration
builds its problem (step windows, model form, nuisances), and adds what the
robust discrepancy carries over from the rig parameters it holds fixed
(:func:`~tembayes.calibrate.discrepancy.held_nuisance_spread`).  The window
sandwich's stretch is left at 1: it measures a disagreement between the
windows that only the real data show.

Averaged over modules drawn from the prior (or a population), these are the
widths a design promises; ``analyses/design_check.py`` compares them with
realised posteriors on both benches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tembayes.constants import MODULE_PARAMETERS


@dataclass(frozen=True)
class Widths:
    """The laws' expected posterior sds on one run.

    Attributes
    ----------
    sd : dict
        Law name -> expected posterior sd [SI].
    mode : dict
        Law name -> the posterior mode the sds were taken at [SI].
    sd_laplace : dict
        Law name -> the Laplace sd alone, without the held rig parameters [SI].
    """

    sd: dict
    mode: dict
    sd_laplace: dict


def _law_slopes(space, x):
    """Law name -> (its coordinate's index, ``d law_SI / d coordinate``, the law's value [SI]) at ``x``."""
    out = {}
    for k in MODULE_PARAMETERS:
        j = space.index(k)
        h = 1e-6 * max(1.0, abs(x[j]))
        up, down, here = space.priors[j].from_unconstrained(np.array([x[j] + h, x[j] - h, x[j]]))
        out[k] = (j, float((up - down) / (2 * h)), float(here))
    return out


def expected_widths(experiment, datasheet, *, rig_config=None, options=None, start=None, max_nfev=30) -> Widths:
    """The laws' expected posterior sds from one identification run (module docstring).

    Parameters
    ----------
    experiment : tembayes.data.Experiment
        The run (a bench simulation of the protocol, or a measured one).
    datasheet : tembayes.data.Datasheet
    rig_config : dict, optional
        The batch's ``[rig]`` table.
    options : CalibrationOptions, optional
        The calibration's model form, resolution and discrepancy method (the
        held rig parameters are carried over with ``"robust"``, the default).
    start : dict, optional
        ``name -> value`` (SI) where the mode search starts, e.g. the
        bench's truth; default the prior centres.
    max_nfev : int
        Model evaluations of the mode search.

    Returns
    -------
    Widths
    """
    from tembayes.calibrate.discrepancy import held_nuisance_spread, held_parameters
    from tembayes.calibrate.module import CalibrationOptions, laplace_fit

    opt = options or CalibrationOptions()
    fit = laplace_fit(experiment, datasheet, rig_config=rig_config, options=opt, start=start, max_nfev=max_nfev)
    space, x, cov, data = fit.space, fit.x, fit.cov, fit.data
    total = cov
    held = held_parameters(fit.model.rig, space)
    if held and opt.discrepancy == "robust":
        nc, n = data.obs.shape
        # the prediction's slopes (p, nc, n) from the whitened residuals' (obs - f) / noise
        J = -(fit.jac[: nc * n].T.reshape(len(x), nc, n)) * data.noise[None, :, None]
        spread = held_nuisance_spread(fit.model, space, x, J, data.noise, held)
        total = cov + (spread.shift * spread.sd**2) @ spread.shift.T
    laws = _law_slopes(space, x)
    return Widths(
        sd={k: abs(d) * float(np.sqrt(total[j, j])) for k, (j, d, _) in laws.items()},
        mode={k: v for k, (_, _, v) in laws.items()},
        sd_laplace={k: abs(d) * float(np.sqrt(cov[j, j])) for k, (j, d, _) in laws.items()},
    )
