"""Figures only the batch report draws (``tembayes report``).

- :func:`plot_module_laws` -- one module's R(T) and S(T) posterior bands over
  the per-step estimates of its identification run;
- :func:`png_bytes` -- a figure as PNG bytes (the report inlines them).
"""

from __future__ import annotations

import io
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

from tembayes.constants import LAW_PARAMETERS

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tembayes.calibrate.run import CalibrationRun

#: Resolution of the report's figures [dots per inch] (small files, sharp enough on screen).
REPORT_DPI = 90


def png_bytes(fig: Figure, dpi: float = REPORT_DPI) -> bytes:
    """``fig`` rendered as PNG (no timestamp in the file: the same figure, the same bytes)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    return buf.getvalue()


def plot_module_laws(
    run: CalibrationRun,
    module_id: str,
    steps: Mapping[str, np.ndarray],
    *,
    max_draws: int = 2000,
    n_temperatures: int = 60,
    fig: Figure | None = None,
) -> Figure:
    """R(T) and S(T) of one module: 90 % posterior band, population band, step estimates.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
    module_id : str
    steps : dict
        From :func:`tembayes.report.content.step_estimates`: ``Tavg_R_C``,
        ``R_ohm``, ``R_sd``, ``Tavg_S_C``, ``S_V_per_K``, ``S_sd``,
        ``direction`` (arrays over the steps; SI but temperatures in degC).
    max_draws : int
    n_temperatures : int
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into (default: a new one).

    Returns
    -------
    matplotlib.figure.Figure
        Two axes: R [ohm] and S [mV/K] against the mean module temperature [degC].
    """
    T_pts = np.concatenate([steps["Tavg_R_C"], steps["Tavg_S_C"]])
    T_pts = T_pts[np.isfinite(T_pts)]
    lo, hi = (T_pts.min() - 2.0, T_pts.max() + 2.0) if T_pts.size else (run.tref_C - 10, run.tref_C + 10)
    T = np.linspace(lo, hi, n_temperatures)
    dT = T - run.tref_C
    q = (0.05, 0.5, 0.95)
    D = run.draws(module_id, LAW_PARAMETERS, max_draws=max_draws)
    bands = [
        np.quantile(D[:, [0]] + D[:, [1]] * dT, q, axis=0),
        np.quantile((D[:, [2]] + D[:, [3]] * dT) * 1e3, q, axis=0),
    ]
    pop = run.population_draws(LAW_PARAMETERS, max_draws=20000)
    fig = fig or Figure(figsize=(11.0, 4.2), layout="constrained")
    axes = fig.subplots(1, 2)
    up = np.asarray(steps["direction"]) == "up"
    pts = [
        (steps["Tavg_R_C"], np.asarray(steps["R_ohm"]), np.asarray(steps["R_sd"])),
        (steps["Tavg_S_C"], np.asarray(steps["S_V_per_K"]) * 1e3, np.asarray(steps["S_sd"]) * 1e3),
    ]
    for k, ax in enumerate(axes):
        if pop is not None:
            P = pop[:, [0]] + pop[:, [1]] * dT if k == 0 else (pop[:, [2]] + pop[:, [3]] * dT) * 1e3
            pb = np.quantile(P, q, axis=0)
            ax.fill_between(T, pb[0], pb[2], color="0.85", lw=0, label="population 90 % (a new module)")
        b = bands[k]
        ax.fill_between(T, b[0], b[2], color="C2", alpha=0.45, lw=0, label=f"{module_id} posterior 90 %")
        ax.plot(T, b[1], color="C2", lw=1.5, label="posterior median")
        x, y, e = pts[k]
        for sel, style in (
            (up, dict(color="C3", marker="^", label="step estimate, up-step")),
            (~up, dict(color="C0", marker="v", label="step estimate, down-step")),
        ):
            ax.errorbar(np.asarray(x)[sel], y[sel], yerr=2 * e[sel], ls="none", ms=5, capsize=2, lw=0.8, **style)
        ax.axvline(run.tref_C, color="0.5", lw=0.8, ls=":")
        ax.set_xlabel("Mean module temperature T [°C]")
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("R [Ω]")
    axes[1].set_ylabel("S [mV/K]")
    axes[0].set_title(f"R(T) = R0 + R1 (T − {run.tref_C:g} °C)")
    axes[1].set_title(f"S(T) = S0 + S1 (T − {run.tref_C:g} °C)")
    axes[1].legend(fontsize=8, loc="best")
    fig.suptitle(f"{module_id}: laws with 90 % bands over the step estimates (±2 sd)")
    return fig
