"""Figures of a Bayesian calibration run (``tembayes calibrate BATCH --out RUN``).

The functions read what the calibration *saved* -- ``RUN/posterior.nc``
(layout in :mod:`tembayes.calibrate.results`) and ``RUN/summary.json``
(docs/outputs.md, 'summary.json (calibrate)') -- through
:func:`load_run`; they never rerun or recompute the calibration, only
quantiles, medians and densities of the stored draws.

- :func:`plot_corner_module` -- one module's posterior (corner plot);
- :func:`plot_corner_population` -- every module's posterior over the
  population predictive of a new module;
- :func:`plot_laws` -- R(T) and S(T) with 90 % bands;
- :func:`plot_hysteresis` -- up-step minus down-step differences of R and S;
- :func:`plot_step_loglike` -- where (in temperature and direction) the model
  fits a module worse;
- :func:`plot_outliers` -- which module is the odd one, and its outlier
  probability against the spread a small batch cannot learn;
- :func:`save_calibration_figures` -- all of them into ``RUN/figures``.

Inside tembayes everything is SI; the figures show ohm, mohm/K, mV/K,
uV/K^2, W/K and degrees Celsius (:data:`DISPLAY_UNITS`).  Figures are
:class:`matplotlib.figure.Figure` objects (no pyplot state).

Large batches stay readable: the overlays show at most
:data:`MAX_OVERLAY_MODULES` modules individually (highest outlier
probability first) and summarise the rest, and the corner plots thin the
draws to at most :data:`MAX_CORNER_DRAWS` per module.
"""

from __future__ import annotations

import io
import math
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator, NullLocator

from tembayes.calibrate.run import CalibrationRun, load_run  # noqa: F401 (re-exported)
from tembayes.constants import LAW_PARAMETERS, MODULE_PARAMETERS
from tembayes.data.batch import file_stem
from tembayes.data.write import atomic_write_bytes

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

__all__ = [
    "CalibrationRun",
    "load_run",
    "plot_corner_module",
    "plot_corner_population",
    "plot_laws",
    "plot_hysteresis",
    "plot_step_loglike",
    "plot_outliers",
    "save_calibration_figures",
    "DISPLAY_UNITS",
]

#: Display label, unit and factor (display = SI x factor) of each parameter.
#: Parameters not listed (rig nuisances) are shown under their own name in SI.
DISPLAY_UNITS = {
    "R0_ohm": (r"$R_0$", "Ω", 1.0),
    "R1_ohm_per_K": (r"$R_1$", "mΩ/K", 1e3),
    "S0_V_per_K": (r"$S_0$", "mV/K", 1e3),
    "S1_V_per_K2": (r"$S_1$", "µV/K²", 1e6),
    "K_W_per_K": (r"$K$", "W/K", 1.0),
}

#: Most per-module corner plots a run writes (a factory batch has thousands).
MAX_CORNER_MODULES = 24
#: Most modules drawn individually in an overlay; the others are summarised.
MAX_OVERLAY_MODULES = 12

#: Most posterior draws per module in a corner plot (evenly thinned).
MAX_CORNER_DRAWS = 4000

#: Most draws per module in the population overlay and the law bands.
MAX_OVERLAY_DRAWS = 2000

#: Most population-predictive draws used in the population overlay.
MAX_POPULATION_DRAWS = 20000

#: Quantiles drawn and quoted in the corner plots.
CORNER_QUANTILES = (0.05, 0.5, 0.95)

#: Probability mass inside the 2-D contours of the overlays.
CONTOUR_LEVELS = (0.5, 0.9)

#: Outlier probability above which a module is flagged in the overlays.
OUTLIER_FLAG = 0.5

#: Hysteresis differences are flagged beyond this many sd.
HYSTERESIS_Z_FLAG = 2.0

#: Resolution of the saved figures [dots per inch].
DPI = 120

# corner's layout numbers (corner.core): panel size, margins [in]
_CORNER_PANEL_IN = 2.0
_CORNER_LB_IN = 0.5 * _CORNER_PANEL_IN
_CORNER_TR_IN = 0.2 * _CORNER_PANEL_IN
_CORNER_WHSPACE = 0.05
# room above the grid for the figure title [in]
_CORNER_TITLE_IN = 0.9

_UP_STYLE = {"color": "C3", "marker": "^", "label": "step up (I increases)"}
_DOWN_STYLE = {"color": "C0", "marker": "v", "label": "step down"}


# --------------------------------------------------------------------------- loading


def _as_run(run):
    return run if isinstance(run, CalibrationRun) else load_run(run)


# --------------------------------------------------------------------------- helpers


def _display(name):
    """``(label, unit, factor)`` of a parameter."""
    return DISPLAY_UNITS.get(name, (name.replace("_", r"\_"), "SI", 1.0))


def _axis_label(name):
    label, unit, _ = _display(name)
    return f"{label} [{unit}]"


def _scale(params):
    return np.array([_display(p)[2] for p in params])


def _p_text(p):
    return "n/a" if p is None else f"{p:.2f}"


def _fmt_interval(mid, lo, hi):
    """``$1.7075^{+0.0019}_{-0.0018}$`` with two significant digits of the smaller error."""
    err = min(abs(hi - mid), abs(mid - lo))
    if not np.isfinite(err) or err <= 0:
        d = 4
    else:
        d = int(min(12, max(0, 1 - math.floor(math.log10(err)))))
    return f"${mid:.{d}f}^{{+{hi - mid:.{d}f}}}_{{-{mid - lo:.{d}f}}}$"


def _ranges(datasets, q=(0.005, 0.995), pad=0.05):
    """Shared ``[lo, hi]`` per column covering every dataset's central quantiles, padded."""
    los = np.min([np.quantile(d, q[0], axis=0) for d in datasets], axis=0)
    his = np.max([np.quantile(d, q[1], axis=0) for d in datasets], axis=0)
    out = []
    for lo, hi in zip(los, his):
        w = hi - lo
        if not w > 0:
            w = abs(lo) * 1e-3 if lo != 0 else 1e-9
            lo, hi = lo - w, hi + w
        out.append((float(lo - pad * w), float(hi + pad * w)))
    return out


def _own_range(x):
    lo, hi = float(np.min(x)), float(np.max(x))
    if not hi > lo:
        w = abs(lo) * 1e-6 if lo != 0 else 1e-12
        lo, hi = lo - w, hi + w
    return (lo, hi)


def _corner_figure(K, fig=None):
    """An empty Figure (``fig``, resized, or a new one) sized as corner sizes its own, plus room for a title."""
    plot = _CORNER_PANEL_IN * K + _CORNER_PANEL_IN * (K - 1) * _CORNER_WHSPACE
    dim = _CORNER_LB_IN + plot + _CORNER_TR_IN
    if fig is None:
        return Figure(figsize=(dim, dim + _CORNER_TITLE_IN)), plot
    if fig.axes:
        raise ValueError("fig must be an empty figure: the corner plot lays out its own grid")
    fig.set_size_inches(dim, dim + _CORNER_TITLE_IN)
    return fig, plot


def _corner_adjust(fig, plot_in):
    """Leave corner's margins but make room for the title on the taller figure."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(
        left=_CORNER_LB_IN / w,
        right=(_CORNER_LB_IN + plot_in) / w,
        bottom=_CORNER_LB_IN / h,
        top=(_CORNER_LB_IN + plot_in) / h,
    )


def _grid(fig, K):
    return np.array(fig.axes).reshape(K, K)


def _module_colors(n):
    """Distinct colours for up to 20 modules (tab10, then tab20's light shades)."""
    import matplotlib

    tab20 = matplotlib.colormaps["tab20"]
    order = list(range(0, 20, 2)) + list(range(1, 20, 2))
    return [tab20(order[i % 20]) for i in range(n)]


def _pick_modules(run, max_n, key=None):
    """Modules to show individually and the rest.

    Default order: highest outlier probability first, then not-converged
    first, then run order.  Return ``(shown, rest)`` in that order / run order.
    """
    mods = list(run.module_ids)
    if len(mods) <= max_n:
        return mods, []
    if key is None:

        def key(m):
            p = run.outlier_prob(m)
            return (-(p if p is not None else -1.0), 0 if run.converged(m) is False else 1)

    pos = {m: i for i, m in enumerate(mods)}
    ranked = sorted(mods, key=lambda m: (key(m), pos[m]))
    shown = ranked[:max_n]
    picked = set(shown)
    return shown, [m for m in mods if m not in picked]


def _check_params(run, params):
    params = tuple(params)
    if not params:
        raise ValueError("params is empty: give at least one parameter name")
    missing = [p for p in params if p not in run.idata.posterior]
    if missing:
        raise ValueError(
            f"parameter(s) {missing} are not in {run.path / 'posterior.nc'}; "
            f"it has {list(run.idata.posterior.data_vars)}"
        )
    return params


# --------------------------------------------------------------------------- corner plots


def _prior_density(run, module_id, name, x_si):
    """Prior density at ``x_si`` (SI) from the module's stored prior, else a KDE of the prior draws, or None."""
    spec = run.priors(module_id).get(name)
    if spec:
        from tembayes.calibrate.priors import ParameterPrior

        try:
            return np.exp(ParameterPrior(name=name, **spec).logpdf(x_si))
        except (TypeError, ValueError):
            pass
    d = run.prior_draws((name,), module_id)
    if d is None or len(d) < 10 or np.ptp(d[:, 0]) <= 0:
        return None
    from scipy.stats import gaussian_kde

    return gaussian_kde(d[:, 0])(x_si)


def plot_corner_module(
    run: CalibrationRun | Path | str,
    module_id: str,
    *,
    params: Sequence[str] = MODULE_PARAMETERS,
    show_prior: bool = False,
    max_draws: int = MAX_CORNER_DRAWS,
    fig: Figure | None = None,
) -> Figure:
    """Corner plot of one module's posterior.

    Diagonal: marginal histograms with the 5, 50 and 95 % quantiles (dashed)
    and a title ``median^{+(q95 - median)}_{-(median - q05)}`` in display
    units; below it, 2-D histograms with contours.  The figure title gives
    the module, its convergence (R-hat max, bulk ESS min; "NOT CONVERGED" in
    red) and its outlier probability ("n/a" without a population fit).

    Parameters
    ----------
    run : CalibrationRun or str or Path
        A loaded run or its folder.
    module_id : str
    params : sequence of str
        Parameters to show (any posterior variable; default the five module
        parameters). Display units: R0 [ohm], R1 [mohm/K], S0 [mV/K],
        S1 [uV/K^2], K [W/K]; others in SI.
    show_prior : bool
        Draw the prior density on the diagonal as a grey dashed line.  The
        posterior is usually far narrower than the datasheet prior, so the
        curve is the prior's *shape* over the shown range, rescaled to half
        the panel height (flat = the data, not the prior, set the posterior).
    max_draws : int
        Draws are thinned evenly to at most this many.
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into (default: a new one).

    Returns
    -------
    matplotlib.figure.Figure
        ``len(params)**2`` axes (corner's grid).
    """
    import corner

    run = _as_run(run)
    run._check(module_id)
    params = _check_params(run, params)
    K = len(params)
    X = run.draws(module_id, params, max_draws=max_draws) * _scale(params)
    if len(X) < 2:
        raise ValueError(f"module {module_id}: fewer than two finite posterior draws in {run.path / 'posterior.nc'}")
    rng = [_own_range(X[:, j]) for j in range(K)]
    fig, plot_in = _corner_figure(K, fig)
    corner.corner(
        X,
        fig=fig,
        labels=[_axis_label(p) for p in params],
        range=rng,
        quantiles=list(CORNER_QUANTILES),
        show_titles=False,
        plot_datapoints=False,
        plot_density=True,
        fill_contours=False,
        levels=CONTOUR_LEVELS,
        smooth=1.0,
        hist_kwargs={"density": True},
        color="C0",
        label_kwargs={"fontsize": 10},
    )
    _corner_adjust(fig, plot_in)
    axes = _grid(fig, K)
    for j, p in enumerate(params):
        ax = axes[j, j]
        lo, mid, hi = np.quantile(X[:, j], CORNER_QUANTILES)
        label, unit, factor = _display(p)
        ax.set_title(f"{label} = {_fmt_interval(mid, lo, hi)} {unit}", fontsize=9)
        if show_prior:
            xg = np.linspace(*rng[j], 200)
            dens = _prior_density(run, module_id, p, xg / factor)
            if dens is not None and np.all(np.isfinite(dens)) and np.max(dens) > 0:
                top = ax.get_ylim()[1]
                ax.plot(xg, dens / np.max(dens) * 0.5 * top, color="0.45", ls="--", lw=1.2, gid=f"prior:{p}")
    p_out = run.outlier_prob(module_id)
    conv = run.converged(module_id)
    n_all = int(np.prod([run.idata.posterior.sizes[d] for d in ("chain", "draw")]))
    fig.suptitle(
        f"Module {module_id} posterior: {run.status(module_id)}; outlier prob {_p_text(p_out)}",
        color="C3" if conv is False else "k",
        fontsize=12,
        y=1.0 - 0.25 / fig.get_size_inches()[1],
        va="top",
    )
    note = f"{len(X)} of {n_all} draws; quantiles 5/50/95 %; contours {', '.join(f'{q:.0%}' for q in CONTOUR_LEVELS)}"
    handles = [Patch(color="C0", alpha=0.6, label="posterior")]
    if show_prior:
        handles.append(Line2D([], [], color="0.45", ls="--", label="prior density (shape over the range, rescaled)"))
    fig.legend(
        handles=handles,
        loc="upper right",
        fontsize=9,
        title=note,
        title_fontsize=8,
        bbox_to_anchor=(1.0 - 0.2 / fig.get_size_inches()[0], 1.0 - 0.9 / fig.get_size_inches()[1]),
    )
    return fig


def _overlay(axes, X, rng, color, *, fill=False, ls="-", own_bins=True, lw=1.3):
    """Draw one dataset on a corner grid: diagonal density, 2-D contours.

    ``own_bins``: bins over the dataset's own span (narrow module posteriors
    get real contours), else over the shared range.  Returns the diagonal
    density peaks.
    """
    import corner

    K = X.shape[1]
    peaks = []
    for j in range(K):
        ax = axes[j, j]
        r = _own_range(X[:, j]) if own_bins else rng[j]
        if fill:
            n, _, _ = ax.hist(
                X[:, j], bins=30, range=r, density=True, histtype="stepfilled", color=color, alpha=0.5, lw=0
            )
        else:
            n, _, _ = ax.hist(X[:, j], bins=20, range=r, density=True, histtype="step", color=color, ls=ls, lw=lw)
        peaks.append(float(np.max(n)))
        for i in range(j + 1, K):
            rr = [_own_range(X[:, j]), _own_range(X[:, i])] if own_bins else [rng[j], rng[i]]
            try:
                corner.hist2d(
                    X[:, j],
                    X[:, i],
                    ax=axes[i, j],
                    range=rr,
                    bins=30 if fill else 20,
                    color=color,
                    levels=CONTOUR_LEVELS,
                    smooth=1.0,
                    quiet=True,
                    plot_datapoints=False,
                    plot_density=False,
                    fill_contours=fill,
                    no_fill_contours=not fill,
                    contour_kwargs={"linestyles": ls, "linewidths": lw},
                    new_fig=False,
                )
            except ValueError:  # too few distinct points for contours
                axes[i, j].plot(np.median(X[:, j]), np.median(X[:, i]), "o", color=color, ms=4)
    return peaks


def _restyle_grid(axes, K):
    """Corner's tick layout again (``corner.hist2d`` resets the axes' scales, and with them the ticks)."""
    for i in range(K):
        for j in range(i + 1):
            ax = axes[i, j]
            ax.xaxis.set_major_locator(MaxNLocator(5, prune="lower"))
            if i != j:
                ax.yaxis.set_major_locator(MaxNLocator(5, prune="lower"))
            ax.tick_params(labelbottom=i == K - 1, labelleft=(j == 0 and i != j))
            if i == K - 1:
                for lab in ax.get_xticklabels():
                    lab.set_rotation(45)
            if j == 0 and i != j:
                for lab in ax.get_yticklabels():
                    lab.set_rotation(45)


def plot_corner_population(
    run: CalibrationRun | Path | str,
    *,
    params: Sequence[str] = MODULE_PARAMETERS,
    max_modules: int = MAX_OVERLAY_MODULES,
    fig: Figure | None = None,
) -> Figure:
    """Every module's posterior over the population predictive of a new module.

    Grey (filled): the population predictive (``population`` group; absent
    without a population fit).  One colour per module: its posterior
    (contours at 50 and 90 % mass, binned on its own span so narrow
    posteriors keep their shape; diagonal: density histogram).  All panels
    share ranges covering everything drawn.  The diagonal densities are on a
    log scale so module posteriors (often ~0.1 % wide) and the population
    (a few % wide) are both visible.  With more than ``max_modules``
    modules, the ``max_modules`` with the highest outlier probability (then
    non-converged ones) are drawn individually and the rest pooled into one
    black dashed distribution.  The legend gives each module's outlier
    probability and marks non-converged modules.

    Parameters
    ----------
    run : CalibrationRun or str or Path
    params : sequence of str
        Parameters (default the five module parameters; display units as in
        :data:`DISPLAY_UNITS`).
    max_modules : int
        Most modules drawn individually.
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into (default: a new one).

    Returns
    -------
    matplotlib.figure.Figure
        ``len(params)**2`` axes.
    """
    import corner

    run = _as_run(run)
    params = _check_params(run, params)
    K = len(params)
    scale = _scale(params)
    shown, rest = _pick_modules(run, max_modules)
    mods = {m: run.draws(m, params, max_draws=MAX_OVERLAY_DRAWS) * scale for m in shown}
    mods = {m: X for m, X in mods.items() if len(X) >= 2}
    pooled = None
    if rest:
        per = max(20, MAX_POPULATION_DRAWS // len(rest))
        parts = [run.draws(m, params, max_draws=per) for m in rest]
        parts = [p for p in parts if len(p)]
        pooled = np.concatenate(parts) * scale if parts else None
    pop = run.population_draws(params, max_draws=MAX_POPULATION_DRAWS)
    pop = None if pop is None else pop * scale
    data = [X for X in [pop, pooled, *mods.values()] if X is not None and len(X) >= 2]
    if not data:
        raise ValueError(f"no finite posterior draws to plot in {run.path / 'posterior.nc'}")
    rng = _ranges(data)
    fig, plot_in = _corner_figure(K, fig)
    # the grid: corner's labels, ticks and ranges, drawn invisibly
    corner.corner(
        data[0],
        fig=fig,
        labels=[_axis_label(p) for p in params],
        range=rng,
        plot_datapoints=False,
        plot_density=False,
        plot_contours=False,
        hist_kwargs={"visible": False},
        label_kwargs={"fontsize": 10},
    )
    _corner_adjust(fig, plot_in)
    axes = _grid(fig, K)
    peaks = []
    handles = []
    if pop is not None:
        peaks.append(_overlay(axes, pop, rng, "0.55", fill=True, own_bins=False))
        handles.append(Patch(color="0.7", label="population predictive (a new module)"))
    if pooled is not None:
        peaks.append(_overlay(axes, pooled, rng, "k", ls="--", own_bins=False, lw=1.0))
        handles.append(Line2D([], [], color="k", ls="--", label=f"other {len(rest)} modules, pooled"))
    for (m, X), color in zip(mods.items(), _module_colors(len(mods))):
        peaks.append(_overlay(axes, X, rng, color))
        p = run.outlier_prob(m)
        flag = " (!)" if p is not None and p > OUTLIER_FLAG else ""
        conv = "" if run.converged(m) is not False else ", NOT CONVERGED"
        handles.append(Line2D([], [], color=color, lw=2, label=f"{m}: outlier prob {_p_text(p)}{flag}{conv}"))
    peaks = np.array(peaks)  # (datasets, K)
    for j in range(K):
        ax = axes[j, j]
        ax.set_xlim(rng[j])
        ax.set_yscale("log")
        top = float(np.max(peaks[:, j]))
        bottom = float(np.min(peaks[:, j])) * 0.02
        ax.set_ylim(bottom if bottom > 0 else top * 1e-4, top * 2.0)
        ax.yaxis.set_major_locator(NullLocator())
        ax.yaxis.set_minor_locator(NullLocator())
        for i in range(j + 1, K):
            axes[i, j].set_xlim(rng[j])
            axes[i, j].set_ylim(rng[i])
    _restyle_grid(axes, K)
    n = len(run.module_ids)
    what = f"{n} module{'s' if n != 1 else ''}"
    if rest:
        what += f" ({len(mods)} shown individually: highest outlier probability first)"
    pop_note = "" if pop is not None else "; no population fit in this run"
    fig.suptitle(
        f"Module posteriors over the population: {what}{pop_note}",
        fontsize=12,
        y=1.0 - 0.25 / fig.get_size_inches()[1],
        va="top",
    )
    w, h = fig.get_size_inches()
    fig.legend(
        handles=handles,
        loc="upper right",
        fontsize=9,
        bbox_to_anchor=(1.0 - 0.2 / w, 1.0 - 0.9 / h),
        title=f"contours {', '.join(f'{q:.0%}' for q in CONTOUR_LEVELS)}; diagonal: density (log)",
        title_fontsize=8,
    )
    return fig


# --------------------------------------------------------------------------- laws


def _law_curves(D, T_C, tref_C):
    """R(T) [ohm] and S(T) [V/K] for every draw row ``(R0, R1, S0, S1)``, shape (n, len(T_C)) each."""
    dT = T_C - tref_C
    R = D[:, [0]] + D[:, [1]] * dT[None, :]
    S = D[:, [2]] + D[:, [3]] * dT[None, :]
    return R, S


def plot_laws(
    run: CalibrationRun | Path | str,
    *,
    max_modules: int = MAX_OVERLAY_MODULES,
    n_temperatures: int = 60,
    fig: Figure | None = None,
) -> Figure:
    """R(T) and S(T) of every module with their 90 % posterior bands.

    Top row: ``R(T) = R0 + R1 (T - Tref)`` [ohm] and
    ``S(T) = S0 + S1 (T - Tref)`` [mV/K] against the mean module temperature
    [degC], over the range of the steps' ``Tavg`` in the run: per module the
    posterior median (line) and the 5-95 % band (shaded) computed from the
    draws, and the population predictive median (dashed) and 90 % band
    (grey) when the run has a population fit.  Bottom row: the same minus a
    reference curve (the population median, else the median over the
    modules' medians) in mohm and uV/K, where the narrow module bands and the
    module-to-module spread are visible.  With more than ``max_modules``
    modules, the others are drawn as thin grey median lines.

    Parameters
    ----------
    run : CalibrationRun or str or Path
    max_modules : int
    n_temperatures : int
        Temperature grid points.
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into (default: a new one).

    Returns
    -------
    matplotlib.figure.Figure
        Four axes: R, S (top), R and S deviations (bottom).
    """
    run = _as_run(run)
    _check_params(run, LAW_PARAMETERS)
    tref = run.tref_C
    Ts = np.concatenate([run.steps(m)["Tavg_C"] for m in run.module_ids])
    Ts = Ts[np.isfinite(Ts)]
    lo, hi = (float(Ts.min()), float(Ts.max())) if Ts.size else (tref - 10.0, tref + 10.0)
    if not hi > lo:
        lo, hi = lo - 5.0, hi + 5.0
    T = np.linspace(lo, hi, n_temperatures)
    shown, rest = _pick_modules(run, max_modules)
    q = (0.05, 0.5, 0.95)
    bands = {}
    for m in run.module_ids:
        D = run.draws(m, LAW_PARAMETERS, max_draws=MAX_OVERLAY_DRAWS if m in shown else 200)
        if len(D) == 0:
            continue
        R, S = _law_curves(D, T, tref)
        bands[m] = (np.quantile(R, q, axis=0), np.quantile(S * 1e3, q, axis=0))
    popD = run.population_draws(LAW_PARAMETERS, max_draws=MAX_POPULATION_DRAWS)
    pop_band = None
    if popD is not None:
        R, S = _law_curves(popD, T, tref)
        pop_band = (np.quantile(R, q, axis=0), np.quantile(S * 1e3, q, axis=0))
    if pop_band is not None:
        ref = (pop_band[0][1], pop_band[1][1])
        ref_label = "population median"
    elif bands:
        ref = tuple(np.median(np.array([b[k][1] for b in bands.values()]), axis=0) for k in (0, 1))
        ref_label = "median of the module medians"
    else:
        raise ValueError(f"no finite posterior draws of {LAW_PARAMETERS} in {run.path / 'posterior.nc'}")
    fig = fig or Figure(figsize=(12.0, 8.0 + 0.18 * int(np.ceil((len(shown) + 3) / 3))), layout="constrained")
    axes = fig.subplots(2, 2, sharex=True)
    # deviations: R in mohm (ohm x 1e3), S in uV/K (mV/K x 1e3)
    dev_factor = (1e3, 1e3)
    colors = dict(zip(shown, _module_colors(len(shown))))
    handles = []
    for k in (0, 1):
        ax, axd = axes[0, k], axes[1, k]
        if pop_band is not None:
            b = pop_band[k]
            ax.fill_between(T, b[0], b[2], color="0.8", lw=0, zorder=0, gid="band:population")
            ax.plot(T, b[1], color="0.35", ls="--", lw=1.4, zorder=1, gid="law:population")
            axd.fill_between(
                T, (b[0] - ref[k]) * dev_factor[k], (b[2] - ref[k]) * dev_factor[k], color="0.8", lw=0, zorder=0
            )
            axd.plot(T, (b[1] - ref[k]) * dev_factor[k], color="0.35", ls="--", lw=1.4, zorder=1)
        for m in rest:
            if m in bands:
                b = bands[m][k]
                ax.plot(T, b[1], color="0.6", lw=0.5, alpha=0.6, zorder=1)
                axd.plot(T, (b[1] - ref[k]) * dev_factor[k], color="0.6", lw=0.5, alpha=0.6, zorder=1)
        for m in shown:
            if m not in bands:
                continue
            b = bands[m][k]
            c = colors[m]
            ls = ":" if run.converged(m) is False else "-"
            ax.fill_between(T, b[0], b[2], color=c, alpha=0.3, lw=0, zorder=2, gid=f"band:{m}")
            ax.plot(T, b[1], color=c, lw=1.5, ls=ls, zorder=3, gid=f"law:{m}")
            axd.fill_between(
                T, (b[0] - ref[k]) * dev_factor[k], (b[2] - ref[k]) * dev_factor[k], color=c, alpha=0.3, lw=0, zorder=2
            )
            axd.plot(T, (b[1] - ref[k]) * dev_factor[k], color=c, lw=1.5, ls=ls, zorder=3)
        for a in (ax, axd):
            a.axvline(tref, color="0.5", lw=0.8, ls=":", zorder=0)
            a.grid(True, alpha=0.3)
        axd.axhline(0.0, color="k", lw=0.8, zorder=1)
        axd.set_xlabel("Mean module temperature T [°C]")
    for m in shown:
        if m in bands:
            bad = run.converged(m) is False
            conv = ", NOT CONVERGED (dotted)" if bad else ""
            handles.append(
                Line2D(
                    [],
                    [],
                    color=colors[m],
                    lw=1.5,
                    ls=":" if bad else "-",
                    label=f"{m}: outlier prob {_p_text(run.outlier_prob(m))}{conv}",
                )
            )
    if rest:
        handles.append(Line2D([], [], color="0.6", lw=0.8, label=f"other {len(rest)} modules (median)"))
    if pop_band is not None:
        handles.append(Patch(color="0.8", label="population predictive 90 % (new module), median dashed"))
    handles.append(Patch(color="C0", alpha=0.3, label="module posterior 5-95 %, median line"))
    axes[0, 0].set_ylabel("Resistance R [Ω]")
    axes[0, 1].set_ylabel("Seebeck coefficient S [mV/K]")
    axes[1, 0].set_ylabel(f"R − {ref_label} [mΩ]")
    axes[1, 1].set_ylabel(f"S − {ref_label} [µV/K]")
    axes[0, 0].set_title(f"R(T) = R0 + R1 (T − {tref:g} °C)")
    axes[0, 1].set_title(f"S(T) = S0 + S1 (T − {tref:g} °C)")
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=8)
    fig.suptitle(f"Temperature laws over the steps' range {lo:.1f}-{hi:.1f} °C ({len(run.module_ids)} modules)")
    return fig


# --------------------------------------------------------------------------- hysteresis


def plot_hysteresis(run: CalibrationRun | Path | str, *, fig: Figure | None = None) -> Figure:
    """Up-step minus down-step difference of R and S per module.

    From ``summary.json`` (``hysteresis``: the calibration's fit of R and S
    raised by h/2 after up-steps and lowered by h/2 after down-steps).  Each
    module: the estimate with a +-2 sd error bar, the zero line (no
    hysteresis) in black; modules with ``|z| > 2`` are red, non-converged
    modules have hollow markers.

    Parameters
    ----------
    run : CalibrationRun or str or Path
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into (default: a new one).

    Returns
    -------
    matplotlib.figure.Figure
        Two axes: R [mohm] and S [uV/K], modules along x.
    """
    run = _as_run(run)
    mods = list(run.module_ids)
    n = len(mods)
    fig = fig or Figure(figsize=(max(7.0, min(20.0, 3.0 + 0.35 * n)), 6.5), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    x = np.arange(n)
    spec = (("R_ohm", 1e3, "R up − down [mΩ]"), ("S_V_per_K", 1e6, "S up − down [µV/K]"))
    for ax, (key, factor, ylabel) in zip(axes, spec):
        est = np.full(n, np.nan)
        sd = np.full(n, np.nan)
        for i, m in enumerate(mods):
            h = run.hysteresis(m).get(key) or {}
            est[i] = np.nan if h.get("estimate") is None else float(h["estimate"]) * factor
            sd[i] = np.nan if h.get("sd") is None else float(h["sd"]) * factor
        ok = np.isfinite(est)
        z = np.where(ok & (sd > 0), est / np.where(sd > 0, sd, 1.0), np.nan)
        flagged = np.abs(z) > HYSTERESIS_Z_FLAG
        conv = np.array([run.converged(m) is not False for m in mods])
        for sel, color in ((ok & ~flagged, "C0"), (ok & flagged, "C3")):
            for cs, filled in ((sel & conv, True), (sel & ~conv, False)):
                if cs.any():
                    ax.errorbar(
                        x[cs],
                        est[cs],
                        yerr=np.where(np.isfinite(sd[cs]), 2 * sd[cs], 0.0),
                        fmt="o",
                        color=color,
                        mfc=color if filled else "none",
                        ms=5,
                        capsize=3,
                        elinewidth=1.0,
                        gid=f"hysteresis:{key}",
                    )
        ax.axhline(0.0, color="k", lw=1.0, zorder=0)
        ax.set_ylabel(ylabel)
        ax.grid(True, axis="y", alpha=0.3)
        if not ok.any():
            ax.text(
                0.5,
                0.5,
                "no hysteresis estimates in summary.json",
                transform=ax.transAxes,
                ha="center",
                va="center",
                color="0.4",
            )
    step = max(1, int(np.ceil(n / 40)))
    axes[1].set_xticks(x[::step])
    axes[1].set_xticklabels([mods[i] for i in x[::step]], rotation=90 if n > 8 else 0, fontsize=8)
    axes[1].set_xlim(-0.6, n - 0.4)
    axes[1].set_xlabel("Module")
    handles = [
        Line2D([], [], color="C0", marker="o", ls="-", label="up − down, ±2 sd"),
        Line2D([], [], color="C3", marker="o", ls="-", label=f"|z| > {HYSTERESIS_Z_FLAG:g}"),
        Line2D([], [], color="0.3", marker="o", mfc="none", ls="none", label="module not converged"),
        Line2D([], [], color="k", lw=1.0, label="no hysteresis"),
    ]
    axes[0].legend(handles=handles, fontsize=8, loc="best", framealpha=0.9)
    axes[0].set_title("Hysteresis: R and S after up-steps minus after down-steps (summary.json)")
    return fig


# --------------------------------------------------------------------------- step log-likelihood


def _per_sample_loglike(run, m):
    """Posterior mean of each step window's log-likelihood per sample [nats], with the steps."""
    st = run.steps(m)
    ll = run.step_loglike(m)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nanmean(ll.reshape(-1, ll.shape[-1]), axis=0) if ll.size else np.zeros(0)
        per = np.where(st["n_samples"] > 0, mean / np.maximum(st["n_samples"], 1), np.nan)
    return per, st


def plot_step_loglike(
    run: CalibrationRun | Path | str,
    *,
    max_modules: int = MAX_OVERLAY_MODULES,
    ncols: int = 3,
    fig: Figure | None = None,
) -> Figure:
    """Per module: how well each step window is fitted, against its temperature.

    For every step window: the posterior mean of its log-likelihood
    (``log_likelihood/step_response``) divided by the number of samples in
    the window (each sample: voltage, dT and mean temperature), against the
    mean module temperature at the step [degC]; red up-triangles after
    up-steps, blue down-triangles after down-steps, a thin grey line in
    step order and the module's median (dashed).  Lower = worse fit; a
    trend with temperature or a split between directions shows what the
    model misses there.  Values compare within a module (they depend on its
    noise level).  With more than ``max_modules`` modules, those whose worst
    step is furthest below their median are shown.

    Parameters
    ----------
    run : CalibrationRun or str or Path
    max_modules : int
    ncols : int
        Panels per row.
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into (default: a new one).

    Returns
    -------
    matplotlib.figure.Figure
        One axes per shown module.
    """
    run = _as_run(run)
    data = {m: _per_sample_loglike(run, m) for m in run.module_ids}

    def spread(m):
        v = data[m][0]
        v = v[np.isfinite(v)]
        return -(float(np.median(v) - np.min(v)) if v.size else -np.inf)

    shown, rest = _pick_modules(run, max_modules, key=spread)
    n = len(shown)
    nc = max(1, min(ncols, n))
    nr = int(np.ceil(n / nc))
    fig = fig or Figure(figsize=(4.3 * nc, 3.3 * nr + 0.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(nr, nc, sharex=True, squeeze=False)).ravel()
    for ax in axes[n:]:
        fig.delaxes(ax)
    for ax, m in zip(axes, shown):
        per, st = data[m]
        T = st["Tavg_C"]
        ok = np.isfinite(per) & np.isfinite(T)
        if ok.any():
            ax.plot(T[ok], per[ok], color="0.75", lw=0.8, zorder=1)
            ax.axhline(float(np.median(per[ok])), color="0.4", ls="--", lw=0.8, zorder=1)
        for style, d in ((_UP_STYLE, 1), (_DOWN_STYLE, -1)):
            sel = ok & (st["direction"] == d)
            if sel.any():
                ax.plot(
                    T[sel],
                    per[sel],
                    ls="none",
                    marker=style["marker"],
                    color=style["color"],
                    ms=6,
                    zorder=3,
                    gid=f"steploglike:{m}",
                )
        other = ok & ~np.isin(st["direction"], (1, -1))
        if other.any():
            ax.plot(T[other], per[other], "o", color="0.3", ms=4, zorder=3)
        if not ok.any():
            ax.text(0.5, 0.5, "no finite step log-likelihoods", transform=ax.transAxes, ha="center", color="0.4")
        conv = run.converged(m)
        ax.set_title(
            f"{m}: outlier prob {_p_text(run.outlier_prob(m))}" + ("; NOT CONVERGED" if conv is False else ""),
            fontsize=10,
            color="C3" if conv is False else "k",
        )
        ax.grid(True, alpha=0.3)
    for i, ax in enumerate(axes[:n]):
        if i % nc == 0:
            ax.set_ylabel("log-lik per sample [nats]")
        if i >= n - nc:
            ax.set_xlabel("Mean module temperature at the step [°C]")
            ax.xaxis.set_tick_params(labelbottom=True)
    handles = [
        Line2D([], [], color=s["color"], marker=s["marker"], ls="none", label=s["label"])
        for s in (_UP_STYLE, _DOWN_STYLE)
    ]
    handles.append(Line2D([], [], color="0.4", ls="--", label="module median"))
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=9)
    what = (
        f"{n} of {len(run.module_ids)} modules, largest drop below their median first"
        if rest
        else f"{n} module{'s' if n != 1 else ''}"
    )
    fig.suptitle(f"Fit per step window: posterior mean log-likelihood per sample ({what})")
    return fig


# --------------------------------------------------------------------------- saving


def plot_outliers(run: CalibrationRun | Path | str, *, fig: Figure | None = None) -> Figure:
    """Which module is the odd one, and what it would take to call it an outlier.

    Left: each module's ``odd_one_prob`` (bars) and ``outlier_prob`` (dots).
    Right: the odd one's outlier probability and odd-one probability given an
    assumed largest spread of its most deviating parameter, and how probable
    that bound is under the batch's own posterior (``outlier_vs_spread``).
    """
    run = _as_run(run)
    summ = run.summary
    if summ.p_any_outlier is None:
        raise ValueError(f"{run.path}: the run has no population fit (or predates odd_one_prob); nothing to draw")
    fig = fig or Figure(figsize=(10.0, 4.0), layout="constrained")
    ax, bx = fig.subplots(1, 2)
    ids = [m for m, e in summ.modules.items() if e.odd_one_prob is not None]
    x = np.arange(len(ids))
    ax.bar(x, [summ.modules[m].odd_one_prob for m in ids], color="C0", alpha=0.7, label="odd_one_prob")
    ax.plot(x, [summ.modules[m].outlier_prob for m in ids], "o", color="C3", label="outlier_prob")
    ax.set_xticks(x, ids, rotation=45 if len(ids) > 6 else 0)
    ax.set_ylim(0, 1)
    ax.set_ylabel("probability")
    ax.set_title(f"which one (P(any outlier) = {summ.p_any_outlier:.2f})")
    ax.legend(loc="upper right")
    curve = summ.outlier_vs_spread
    if curve:
        rows = curve["rows"]
        sp = np.array([r["spread_max"] for r in rows])
        level = curve["parameter"] in ("R0_ohm", "S0_V_per_K", "K_W_per_K")
        sx = 100 * sp if level else sp

        def col(k):
            return np.array([np.nan if r[k] is None else r[k] for r in rows], dtype=float)

        bx.plot(sx, col("outlier_prob"), "o-", color="C3", label=f"{curve['module']} an outlier")
        bx.plot(sx, col("odd_one_prob"), "s-", color="C0", label=f"{curve['module']} the odd one, if one")
        bx.plot(sx, col("posterior_mass"), "k--", label="P(spread ≤ s | batch)")
        bx.set_xscale("log")
        bx.xaxis.set_minor_locator(NullLocator())
        bx.set_xticks(sx, [f"{v:.2g}" for v in sx])
        name = curve["parameter"].split("_")[0]
        bx.set_xlabel(f"assumed largest unit-to-unit spread of {name}, s" + (" [%]" if level else " [SI]"))
        bx.set_ylim(0, 1.02)
        bx.set_title("what it would take")
        bx.legend(loc="best", fontsize="small")
    return fig


def _save(fig, path, fmt, dpi):
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=dpi)
    return atomic_write_bytes(path, buf.getvalue())


def save_calibration_figures(
    run_dir: Path | str, *, fmt: str = "png", dpi: float = DPI, max_corner_modules: int = MAX_CORNER_MODULES
) -> list[Path]:
    """Write the figures of a calibration run into ``RUN/figures``.

    Files, each written atomically (replacing older ones): ``corner_<id>``
    per module (:func:`plot_corner_module`; in a batch of more than
    ``max_corner_modules``, for that many: the highest outlier probabilities
    first, as in the overlays), ``corner_population``,
    ``laws``, ``hysteresis``, ``step_loglike`` and (with a population fit)
    ``outliers``, with the extension
    ``fmt``.  Module ids are made file-name safe (characters other than
    letters, digits, ``.``, ``_``, ``-`` become ``_``).

    Parameters
    ----------
    run_dir : str or Path
        The run folder (``posterior.nc``, ``summary.json``).
    fmt : str
        A matplotlib output format ("png", "pdf", "svg").
    dpi : float
        Resolution [dots per inch].
    max_corner_modules : int
        Most per-module corner plots.

    Returns
    -------
    list of Path
        The written files, in the order above.
    """
    run = load_run(run_dir)
    out = run.path / "figures"
    written = []
    for m in _pick_modules(run, max_corner_modules)[0]:
        written.append(_save(plot_corner_module(run, m), out / f"corner_{file_stem(m)}.{fmt}", fmt, dpi))
    written.append(_save(plot_corner_population(run), out / f"corner_population.{fmt}", fmt, dpi))
    written.append(_save(plot_laws(run), out / f"laws.{fmt}", fmt, dpi))
    written.append(_save(plot_hysteresis(run), out / f"hysteresis.{fmt}", fmt, dpi))
    written.append(_save(plot_step_loglike(run), out / f"step_loglike.{fmt}", fmt, dpi))
    if run.summary.p_any_outlier is not None:
        written.append(_save(plot_outliers(run), out / f"outliers.{fmt}", fmt, dpi))
    return written
