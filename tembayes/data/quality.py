"""Quick numbers about an experiment, for ``tembayes inspect`` and the report."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..constants import KELVIN

if TYPE_CHECKING:  # the experiment's checks use this module's noise estimate
    from numpy.typing import ArrayLike

    from .experiment import Experiment

__all__ = ["summarize_experiment", "noise_estimate", "CURRENT_LEVEL_STEP_A"]

#: Currents are rounded to this before counting distinct levels [A].
CURRENT_LEVEL_STEP_A = 0.05
#: 1.4826 * MAD estimates the standard deviation of Gaussian data.
_MAD_TO_SD = 1.4826


def noise_estimate(values: ArrayLike) -> float:
    """Robust white-noise level of a slowly varying signal.

    Parameters
    ----------
    values : array_like, shape (n,)
        Samples, in any unit.

    Returns
    -------
    float
        ``1.4826 * MAD(second differences) / sqrt(6)``, in the unit of
        ``values``.  Second differences cancel the signal's local slope (a
        thermal transient sampled at 1 Hz moves tens of mK between samples,
        which first differences would count as noise); the median ignores
        the few large values at steps; ``sqrt(6)`` is the standard deviation
        of ``x[i+1] - 2 x[i] + x[i-1]`` for unit white noise.  NaN for fewer
        than 3 samples.
    """
    d = np.diff(np.asarray(values, dtype=np.float64), n=2)
    if d.size == 0:
        return math.nan
    mad = np.median(np.abs(d - np.median(d)))
    return float(_MAD_TO_SD * mad / math.sqrt(6.0))


def summarize_experiment(exp: Experiment) -> dict:
    """Summary numbers of one experiment, in CSV units.

    Parameters
    ----------
    exp : Experiment

    Returns
    -------
    dict
        Plain Python numbers (ints for counts, floats otherwise):

        - ``n_samples``, ``duration_s``, ``t_start_s``, ``t_end_s``,
          ``dt_median_s``, ``dt_min_s``, ``dt_max_s`` [s]
        - ``current_min_A``, ``current_max_A`` [A],
          ``voltage_min_V``, ``voltage_max_V`` [V]
        - ``n_current_levels``: distinct currents after rounding to 0.05 A
          (rough: noise near a rounding edge can add a level)
        - ``<T>_min``, ``<T>_max`` for each temperature column ``<T>``
          (the rig's sensors and boundaries) [degC]
        - ``<col>_noise`` for every measured column (current_A, voltage_V and
          the temperatures), robust white-noise sd in the column's CSV unit
          (A, V, degC = K); see :func:`noise_estimate`.
    """
    t = exp.time
    dt = np.diff(t)
    out = {
        "n_samples": int(exp.n),
        "duration_s": float(exp.duration),
        "t_start_s": float(t[0]),
        "t_end_s": float(t[-1]),
        "dt_median_s": float(np.median(dt)) if dt.size else math.nan,
        "dt_min_s": float(dt.min()) if dt.size else math.nan,
        "dt_max_s": float(dt.max()) if dt.size else math.nan,
        "current_min_A": float(exp.current.min()),
        "current_max_A": float(exp.current.max()),
        "voltage_min_V": float(exp.voltage.min()),
        "voltage_max_V": float(exp.voltage.max()),
        "n_current_levels": int(np.unique(np.round(exp.current / CURRENT_LEVEL_STEP_A)).size),
    }
    for c in exp.sensor_names + exp.boundary_names:
        v = exp.channel(c) - KELVIN
        out[f"{c}_min"] = float(v.min())
        out[f"{c}_max"] = float(v.max())
    for c in exp.columns[1:]:  # every measured column; time is the axis
        out[f"{c}_noise"] = noise_estimate(exp.channel(c))  # K and degC noise are equal
    return out
