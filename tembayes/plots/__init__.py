"""Figures: plotting functions that read the plain result objects of the pipeline.

Every function draws on a :class:`matplotlib.figure.Figure` (no pyplot global
state), takes an optional ``fig=``/``ax=`` to draw into and returns the
Figure.  Inside tembayes everything is SI; the figures show degrees Celsius
and the CSV units.
"""

from tembayes.plots.calibrate import (
    load_run,
    plot_corner_module,
    plot_corner_population,
    plot_hysteresis,
    plot_laws,
    plot_step_loglike,
    save_calibration_figures,
)
from tembayes.plots.identify import (
    plot_error_vs_tavg,
    plot_identification_run,
    plot_law,
    plot_validation,
    save_identify_figures,
)

__all__ = [
    "plot_identification_run",
    "plot_law",
    "plot_validation",
    "plot_error_vs_tavg",
    "save_identify_figures",
    "load_run",
    "plot_corner_module",
    "plot_corner_population",
    "plot_laws",
    "plot_hysteresis",
    "plot_step_loglike",
    "save_calibration_figures",
]
