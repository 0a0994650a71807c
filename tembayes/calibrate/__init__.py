"""Bayesian calibration of a batch (``tembayes calibrate``).

The pipeline: ``stepdata`` (the run cut into step windows) -> ``model`` (the step-response
model, exact and expanded) -> ``likelihood`` (noise and window offsets) with
``priors``/``parameters`` -> ``sampler`` (emcee until converged,
checkpointed) -> ``module`` (one module's posterior) -> ``scaleout`` (where
the modules run: this process, or a local or remote Dask cluster) ->
``population`` (the batch's population and outlier probabilities) -> ``batch``
(the run) -> ``results`` (``posterior.nc``, ``summary.json``).

    >>> from tembayes.data import load_batch
    >>> from tembayes.calibrate import calibrate_batch
    >>> summary = calibrate_batch(load_batch("data/example"), "runs/example", seed=0)  # doctest: +SKIP
    >>> big = load_batch("factory/lot42", lazy=True)  # validated, then only paths kept  # doctest: +SKIP
    >>> summary = calibrate_batch(big, "runs/lot42", workers=8)  # doctest: +SKIP
"""

from tembayes.calibrate.batch import calibrate_batch
from tembayes.calibrate.module import CalibrationOptions, ModuleCalibration, calibrate_module

__all__ = ["calibrate_batch", "calibrate_module", "CalibrationOptions", "ModuleCalibration"]
