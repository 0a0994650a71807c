"""The posterior predictive of an experiment as ArviZ InferenceData (``DIR/predictive.nc``).

Groups, every data variable with a ``units`` attribute (as in ``posterior.nc``):

- ``posterior_predictive``: per channel (the rig's sensor columns [K],
  ``voltage_V`` [V]) every predictive draw with its noise, dims
  ``(chain, draw, time)`` (one chain: the draws are independent), the values
  the bands of ``metrics.json`` are quantiles of;
- ``observed_data``: the measured channels, dims ``(time,)``;
- ``constant_data``: the measured current [A] and the time since the last
  current step [s], dims ``(time,)``.

The coordinate ``time`` is the experiment's sample times [s].  Channels keep
their CSV names and hold SI values (K; a deviation in K is one in degC), so
``az.plot_ppc(idata, var_names=[SENSOR])`` compares like with like.  The
noise of a draw is white with the sd of the channel's residual process (as
in the bands); its correlation in time is not drawn.
"""

from __future__ import annotations

import numpy as np

import tembayes
from tembayes.predict.runmodel import VOLTAGE

#: File name of the predictive in a ``tembayes predict`` output folder.
PREDICTIVE_FILE = "predictive.nc"
#: Units of the ``constant_data`` variables.
CONSTANT_UNITS = {"current_A": "A", "time_since_step_s": "s"}


def to_inference_data(result):
    """The linear-law predictive of a :class:`~tembayes.predict.predictive.PredictResult` as InferenceData.

    Parameters
    ----------
    result : PredictResult
        From :func:`~tembayes.predict.predictive.predict` with ``keep_predictive=True``.

    Returns
    -------
    arviz.InferenceData
        Groups ``posterior_predictive``, ``observed_data``, ``constant_data``.

    Raises
    ------
    ValueError
        The prediction did not keep its draws.
    """
    import xarray as xr

    from tembayes.common.arvizlib import az

    p = result.linear
    if p.predictive is None:
        raise ValueError("the prediction kept no draws: call predict(..., keep_predictive=True)")
    time = {"time": p.time}
    pp = xr.Dataset(
        {ch: (("chain", "draw", "time"), p.predictive[None, :, c]) for c, ch in enumerate(p.channels)},
        coords={"chain": [0], "draw": np.arange(p.predictive.shape[0]), **time},
    )
    obs = xr.Dataset({ch: (("time",), p.measured[c]) for c, ch in enumerate(p.channels)}, coords=time)
    channel_units = {c: "V" if c == VOLTAGE else "K" for c in p.channels}
    since = p.since_step if p.since_step is not None else np.full(len(p.time), np.nan)
    const = xr.Dataset({"current_A": (("time",), p.current), "time_since_step_s": (("time",), since)}, coords=time)
    for ds, units in ((pp, channel_units), (obs, channel_units), (const, CONSTANT_UNITS)):
        for name, unit in units.items():
            ds[name].attrs["units"] = unit
        ds["time"].attrs["units"] = "s"
        ds.attrs.update(_attrs(result))
    return az.InferenceData(posterior_predictive=pp, observed_data=obs, constant_data=const)


def _attrs(result):
    """What the predictive is of (every group's attributes)."""
    p = result.linear
    return {
        "tembayes_module": p.label,
        "tembayes_experiment": p.source,
        "tembayes_laws": p.laws,
        "tembayes_seed": int(result.seed),
        "tembayes_n_failed_draws": int(p.n_failed),
        "tembayes_version": tembayes.__version__,
        "tembayes_noise": "white, the sd of the channel's residual process in each draw (as in the bands)",
    }


def write_predictive(result, path):
    """Write :func:`to_inference_data` of ``result`` to ``path`` (netCDF4/HDF5) atomically.

    Returns
    -------
    Path
    """
    from tembayes.calibrate.results import write_netcdf

    return write_netcdf(to_inference_data(result), path)
