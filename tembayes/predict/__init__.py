"""Stage 4 -- posterior-predictive simulation of experiments (``tembayes predict``).

- :mod:`~tembayes.predict.runmodel`: a whole run as the calibration model sees it;
- :mod:`~tembayes.predict.anchor`: the rig parameters the step likelihood leaves
  open, anchored on the identification run; the residual processes;
- :mod:`~tembayes.predict.predictive`: draws, bands, metrics, ``predict``;
- :mod:`~tembayes.predict.inference`: the predictive as ArviZ InferenceData
  (``predictive.nc``; imported on its own: it loads arviz).
"""

from tembayes.predict.anchor import anchor_rig, unpinned
from tembayes.predict.predictive import Prediction, PredictResult, constant_laws, predict, simulate_predictive
from tembayes.predict.runmodel import VOLTAGE, RunModel

__all__ = [
    "RunModel",
    "VOLTAGE",
    "anchor_rig",
    "unpinned",
    "predict",
    "simulate_predictive",
    "constant_laws",
    "Prediction",
    "PredictResult",
]
