"""Figures of the deterministic identification (the paper's Figures 5-9).

The functions read what :mod:`tembayes.identify.pipeline` returns
(:class:`~tembayes.identify.pipeline.ModuleIdentification`, the
:class:`~tembayes.physics.simulate.Simulation` of each validation run) and the
loaded :class:`~tembayes.data.Experiment`; they compute nothing the pipeline
did not, apart from residuals and their binned RMS.

- :func:`plot_identification_run` -- Fig. 5: current, voltage, sensor dT;
- :func:`plot_law` -- Fig. 6 (R_m) and Fig. 7 (S_m): per-step estimates and
  fitted laws;
- :func:`plot_validation` -- Figs. 8/9: measured vs simulated sensors and
  the residuals;
- :func:`plot_error_vs_tavg` -- why the constant model fails away from
  35 degC;
- :func:`save_identify_figures` -- all of them as PNG files.

Everything inside is SI; the figures show degC, K (differences), A, V,
ohm and mV/K.  Library code draws on :class:`matplotlib.figure.Figure`
objects only (no pyplot state), so it is safe in scripts, servers and tests.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from tembayes.constants import KELVIN, T_REF
from tembayes.data.write import atomic_write_bytes

if TYPE_CHECKING:
    from collections.abc import Mapping

    from matplotlib.axes import Axes

    from tembayes.data import Batch, Experiment
    from tembayes.identify.pipeline import ModuleIdentification
    from tembayes.physics.simulate import Simulation

__all__ = [
    "plot_identification_run",
    "plot_law",
    "plot_validation",
    "plot_error_vs_tavg",
    "save_identify_figures",
]

#: The paper's model accuracy claim, +-0.5 degC (drawn as a band) [K].
ACCURACY_BAND_K = 0.5

#: The temperature at which the constant model freezes R and S [degC].
CONSTANT_MODEL_T_C = 35.0

#: Width of the temperature bins of :func:`plot_error_vs_tavg` [K].
BIN_WIDTH_K = 2.0

#: Bins with fewer samples than this get no RMS point (a few samples of a
#: fast transient would otherwise draw a spike).
MIN_BIN_SAMPLES = 10

#: Sensor colours, in the rig's order (on the reference rig: the hot side warm, the cold side cool).
SENSOR_COLORS = ("C1", "C3", "C0", "C9", "C4", "C5", "C6", "C8")

#: Resolution of the saved PNG files [dots per inch].
DPI = 120

# Marker per step direction: up and down steps at similar temperatures side
# by side show hysteresis at a glance.
_DIRECTION_MARKERS = {"up": "^", "down": "v"}

# What plot_law draws for each law: where the estimates live in a step row,
# the display scale and labels.
_LAWS = {
    "R": {
        "line": "R",
        "scale": 1.0,
        "ylabel": "R_m [ohm]",
        "hyst_decimals": 4,
        "X0": "R0_ohm",
        "X1": "R1_ohm_per_K",
        "title": "Electrical resistance R_m(T_avg) (paper Fig. 6)",
        "paper_label": "paper recipe (first sample, sensor T)",
    },
    "S": {
        "line": "S",
        "scale": 1e3,
        "ylabel": "S_m [mV/K]",
        "hyst_decimals": 3,
        "X0": "S0_V_per_K",
        "X1": "S1_V_per_K2",
        "title": "Seebeck coefficient S_m(T_avg) (paper Fig. 7)",
        "paper_label": "paper recipe (sensor dT and T)",
    },
}


def _module_color(i):
    """The i-th module's colour (C0, C1, ... like the paper's TEM1..3)."""
    return f"C{i % 10}"


def _empty_figure(fig, figsize):
    """A new constrained-layout Figure, or check that the given one is empty."""
    if fig is None:
        return Figure(figsize=figsize, layout="constrained")
    if fig.axes:
        raise ValueError(f"fig must be an empty Figure, found one with {len(fig.axes)} axes")
    return fig


def _hours(exp):
    """Time since the first sample [h]."""
    return (exp.time - exp.time[0]) / 3600.0


def _sim_sensors(exp, sim):
    """Draw 0 of a simulation's sensors on the experiment's time grid, shape (ns, n) [K]."""
    T = np.asarray(sim.sensors)[0]
    st = np.asarray(sim.time)
    if st.shape == exp.time.shape and np.allclose(st, exp.time):
        return T
    # a decimated simulation: linear interpolation is ample for block
    # temperatures that move over minutes
    return np.vstack([np.interp(exp.time, st, Tc) for Tc in T])


def _run_name(exp):
    """``<module folder>/<file name>`` of a run, for titles."""
    parent = exp.path.parent.name
    return f"{parent}/{exp.path.name}" if parent else exp.path.name


def _channel_names(sim):
    return [str(ch).removesuffix("_C") for ch in sim.channels]


def plot_identification_run(
    experiments: Mapping[str, Experiment], *, face: tuple[str, str], fig: Figure | None = None
) -> Figure:
    """The identification runs of a batch (the paper's Fig. 5).

    Three stacked panels over a shared time axis: module current, terminal
    voltage and the temperature difference of the face sensors across the
    module, one colour per module (C0, C1, ... as the paper's TEM1..3).

    Parameters
    ----------
    experiments : dict of str to Experiment
        Module id -> its identification run (SI: s, A, V, K).
    face : tuple of (str, str)
        The hot- and cold-face sensor columns (the rig's ``layout.face``).
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into; a new one (9 x 7.5 in) if absent.

    Returns
    -------
    matplotlib.figure.Figure
        With three axes: current [A], voltage [V], dT [K], time in hours
        since each run's first sample; the module traces carry
        ``gid="run:<module>"``.
    """
    if not experiments:
        raise ValueError("experiments is empty: give at least one module's identification run")
    fig = _empty_figure(fig, (9.0, 7.5))
    ax_i, ax_v, ax_dt = fig.subplots(3, 1, sharex=True)
    for i, (mid, exp) in enumerate(experiments.items()):
        color = _module_color(i)
        t = _hours(exp)
        ax_i.plot(t, exp.current, color=color, lw=1.0, label=mid, gid=f"run:{mid}")
        ax_v.plot(t, exp.voltage, color=color, lw=0.8, gid=f"run:{mid}")
        ax_dt.plot(t, exp.channel(face[0]) - exp.channel(face[1]), color=color, lw=1.0, gid=f"run:{mid}")
    for ax in (ax_i, ax_v, ax_dt):
        ax.axhline(0.0, color="0.6", lw=0.6, zorder=0)
        ax.grid(True, alpha=0.3)
    ax_i.set_ylabel("Current I [A]")
    ax_v.set_ylabel("Voltage V [V]")
    hot, cold = (c.removesuffix("_C") for c in face)
    ax_dt.set_ylabel(f"Sensor ΔT = {hot} − {cold} [K]")
    ax_dt.set_xlabel("Time since start of run [h]")
    ax_i.legend(ncols=min(len(experiments), 6), loc="upper right", fontsize=9)
    ax_i.set_title("Identification run: current staircase (paper Fig. 5)")
    return fig


def _law_points(rows, which, scale):
    """Per-step estimates of one law from a module's step table, in display units.

    Returns
    -------
    dict of ndarray
        ``T`` [degC], ``y``, ``sd``, ``T_sd`` [K], ``direction``, and the
        paper recipe's ``T_paper`` [degC], ``y_paper``.
    """
    if which == "R":
        T = [r["Tavg_R"] for r in rows]
        T_sd = [r.get("Tavg_R_sd", np.nan) for r in rows]
        y = [r["jump"].R for r in rows]
        sd = [r["jump"].R_sd for r in rows]
        Tp = [r["Tavg_R_paper"] for r in rows]
        yp = [r["jump"].R_first for r in rows]
    else:
        T = [r["Tavg"] for r in rows]
        # the two junction temperatures' errors, taken as independent
        T_sd = [0.5 * float(np.hypot(r.get("Th_sd", np.nan), r.get("Tc_sd", np.nan))) for r in rows]
        y = [r["S"] for r in rows]
        sd = [r["S_sd"] for r in rows]
        Tp = [r["Tavg_paper"] for r in rows]
        yp = [r["S_paper"] for r in rows]

    def f(v):
        return np.asarray(v, dtype=float)

    return {
        "T": f(T) - KELVIN,
        "T_sd": f(T_sd),
        "y": f(y) * scale,
        "sd": f(sd) * scale,
        "direction": np.array([r["direction"] for r in rows]),
        "T_paper": f(Tp) - KELVIN,
        "y_paper": f(yp) * scale,
    }


def _hysteresis_note(res, which):
    """``"; up − down +0.001 ± 0.002 ohm"`` from the pipeline's hysteresis test, or ``""``."""
    h = (getattr(res, "hysteresis", None) or {}).get(which) or {}
    if h.get("diff") is None or h.get("sd") is None:
        return ""
    spec = _LAWS[which]
    unit = spec["ylabel"].split("[")[1].rstrip("]")
    d = spec["hyst_decimals"]
    return f"; up − down {h['diff'] * spec['scale']:+.{d}f} ± {h['sd'] * spec['scale']:.{d}f} {unit}"


def plot_law(
    results: Mapping[str, ModuleIdentification],
    which: str,
    *,
    average: Mapping[str, float] | None = None,
    ax: Axes | None = None,
    paper: bool = True,
) -> Figure:
    """Per-step estimates and fitted linear law of R_m or S_m (the paper's Figs. 6 and 7).

    For each module (colour C0, C1, ...): the step estimates with their
    1-sd error bars (``^`` up-steps, ``v`` down-steps, so hysteresis shows as
    a systematic offset between the two; the legend quotes the pipeline's
    up-minus-down difference at equal temperature when it has one), the
    fitted line (solid) over the module's temperature range with a shaded
    +-1 sd band of the law, and, with ``paper=True``, the paper's literal
    recipe as faint hollow markers so its bias against the corrected
    estimates is visible.  The batch average law is drawn dashed black.

    Parameters
    ----------
    results : dict of str to ModuleIdentification
        Module id -> what :func:`tembayes.identify.pipeline.identify_module`
        returned.
    which : {"R", "S"}
        The resistance [ohm] or the Seebeck coefficient (shown in mV/K).
    average : dict, optional
        :func:`tembayes.identify.pipeline.batch_average` output (SI:
        ``R0_ohm``, ``R1_ohm_per_K``, ``S0_V_per_K``, ``S1_V_per_K2``); the
        law is ``X0 + X1 (T - 25 degC)``.  No average line if absent.
    ax : matplotlib.axes.Axes, optional
        Where to draw; a new figure (7.5 x 5 in) if absent.
    paper : bool
        Also show the paper recipe's estimates (R: first sample after the
        step against the sensor mean temperature; S: sensor dT and sensor
        mean temperature).

    Returns
    -------
    matplotlib.figure.Figure
        The fitted lines carry ``gid="law:<module>"`` and the average
        ``gid="law:average"``.
    """
    if which not in _LAWS:
        raise ValueError(f"which must be one of {sorted(_LAWS)}, got {which!r}")
    if not results:
        raise ValueError("results is empty: give at least one module's identification")
    spec = _LAWS[which]
    scale = spec["scale"]
    if ax is None:
        fig = Figure(figsize=(7.5, 5.0), layout="constrained")
        ax = fig.add_subplot()
    else:
        fig = ax.get_figure()
    handles = []
    T_all = []
    for i, (mid, res) in enumerate(results.items()):
        color = _module_color(i)
        pts = _law_points(res.steps, which, scale)
        ok = np.isfinite(pts["T"]) & np.isfinite(pts["y"])  # S is NaN at holds with too small dT
        if paper:
            okp = np.isfinite(pts["T_paper"]) & np.isfinite(pts["y_paper"])
            for d, marker in _DIRECTION_MARKERS.items():
                m = okp & (pts["direction"] == d)
                ax.scatter(
                    pts["T_paper"][m],
                    pts["y_paper"][m],
                    marker=marker,
                    s=30,
                    facecolors="none",
                    edgecolors=color,
                    linewidths=0.9,
                    alpha=0.45,
                    zorder=2,
                    gid=f"paper:{mid}",
                )
        for d, marker in _DIRECTION_MARKERS.items():
            m = ok & (pts["direction"] == d)
            if m.any():
                ax.errorbar(
                    pts["T"][m],
                    pts["y"][m],
                    yerr=pts["sd"][m],
                    xerr=pts["T_sd"][m],
                    fmt=marker,
                    color=color,
                    ms=5,
                    elinewidth=0.8,
                    capsize=0,
                    zorder=4,
                )
        if ok.any():
            T_all.append(pts["T"][ok])
            line = res.lines[spec["line"]]
            Tg = np.linspace(pts["T"][ok].min(), pts["T"][ok].max(), 60)
            TK = Tg + KELVIN
            y, s = line(TK) * scale, line.sd(TK) * scale
            ax.fill_between(Tg, y - s, y + s, color=color, alpha=0.2, lw=0, zorder=1, gid=f"band:{mid}")
            ax.plot(Tg, y, color=color, lw=1.8, zorder=3, gid=f"law:{mid}")
        handles.append(Line2D([], [], color=color, lw=1.8, label=f"{mid}: fitted law" + _hysteresis_note(res, which)))
    if average is not None and T_all:
        T = np.concatenate(T_all)
        Tg = np.linspace(T.min(), T.max(), 60)
        y = (average[spec["X0"]] + average[spec["X1"]] * (Tg + KELVIN - T_REF)) * scale
        ax.plot(Tg, y, color="k", ls="--", lw=1.6, zorder=5, gid="law:average")
        handles.append(Line2D([], [], color="k", ls="--", lw=1.6, label="batch average"))
    handles += [
        Patch(facecolor="0.5", alpha=0.3, label="±1 sd of the law"),
        Line2D([], [], color="0.3", marker="^", ls="none", label="step up (I increases)"),
        Line2D([], [], color="0.3", marker="v", ls="none", label="step down"),
    ]
    if paper:
        handles.append(
            Line2D([], [], color="0.3", marker="^", mfc="none", ls="none", alpha=0.6, label=spec["paper_label"])
        )
    ax.legend(handles=handles, fontsize=8, loc="best", framealpha=0.9)
    ax.set_xlabel("Mean module temperature T_avg [°C]")
    ax.set_ylabel(spec["ylabel"])
    ax.set_title(spec["title"])
    ax.grid(True, alpha=0.3)
    return fig


def plot_validation(exp: Experiment, sim: Simulation, *, title: str | None = None, fig: Figure | None = None) -> Figure:
    """Measured against simulated sensor temperatures of one run (the paper's Figs. 8 and 9).

    Top panel: the rig's sensors measured (solid) and simulated (dashed)
    [degC], in the rig's order (on the reference rig the hot side in warm
    colours, the cold side in cool ones).  Bottom panel: residuals measured - simulated [K] with the
    paper's +-0.5 K accuracy claim as a grey band and each sensor's RMSE in
    the legend.

    Parameters
    ----------
    exp : Experiment
        The measured run (SI).
    sim : Simulation
        Its simulation; draw 0 is used.  Interpolated onto ``exp.time`` if
        simulated on another grid.
    title : str, optional
        Figure title; the file name if absent.
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into; a new one (10 x 6.5 in) if absent.

    Returns
    -------
    matplotlib.figure.Figure
        With two axes (temperatures, residuals) over time [h]; the traces
        carry ``gid`` ``"measured:<sensor>"``, ``"simulated:<sensor>"``, ``"residual:<sensor>"``.
    """
    fig = _empty_figure(fig, (10.0, 6.5))
    ax_t, ax_r = fig.subplots(2, 1, sharex=True, height_ratios=[2, 1])
    t = _hours(exp)
    Tsim = _sim_sensors(exp, sim)
    names = _channel_names(sim)
    handles = []
    for c, name in enumerate(names):
        color = SENSOR_COLORS[c % len(SENSOR_COLORS)]
        measured = exp.channel(sim.channels[c])
        ax_t.plot(t, measured - KELVIN, color=color, lw=1.2, gid=f"measured:{name}")
        ax_t.plot(t, Tsim[c] - KELVIN, color=color, lw=1.2, ls="--", gid=f"simulated:{name}")
        r = measured - Tsim[c]
        rmse = float(np.sqrt(np.mean(r**2)))
        ax_r.plot(t, r, color=color, lw=0.9, label=f"{name}: RMSE {rmse:.2f} K", gid=f"residual:{name}")
        handles.append(Line2D([], [], color=color, lw=1.5, label=name))
    handles += [
        Line2D([], [], color="0.3", lw=1.2, label="measured"),
        Line2D([], [], color="0.3", lw=1.2, ls="--", label="simulated"),
    ]
    # legends beside the panels: the traces fill the whole time axis
    ax_t.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax_t.set_ylabel("Temperature [°C]")
    ax_t.grid(True, alpha=0.3)
    ax_r.axhspan(
        -ACCURACY_BAND_K, ACCURACY_BAND_K, color="0.88", zorder=0, label=f"±{ACCURACY_BAND_K:g} K (paper's accuracy)"
    )
    ax_r.axhline(0.0, color="0.5", lw=0.6, zorder=0)
    ax_r.set_ylabel("Measured − simulated [K]")
    ax_r.set_xlabel("Time since start of run [h]")
    ax_r.grid(True, alpha=0.3)
    ax_r.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax_t.set_title(title if title is not None else f"Validation: {_run_name(exp)}")
    return fig


def _binned_rms(x, r, edges, min_count=MIN_BIN_SAMPLES):
    """RMS of ``r`` in bins of ``x``; bin centres and RMS of the bins with enough samples."""
    idx = np.digitize(x, edges) - 1
    centres, rms = [], []
    for b in range(len(edges) - 1):
        m = idx == b
        if m.sum() >= min_count:
            centres.append(0.5 * (edges[b] + edges[b + 1]))
            rms.append(float(np.sqrt(np.mean(r[m] ** 2))))
    return np.array(centres), np.array(rms)


def plot_error_vs_tavg(
    exp: Experiment, sims: Mapping[str, Simulation], *, face: tuple[str, str], fig: Figure | None = None
) -> Figure:
    """Cold-side sensor error against the mean sensor temperature, for several models.

    The paper's argument for temperature-dependent laws: a model with R and
    S frozen at 35 degC is right near 35 degC and drifts away from it.  For
    each model: the cold-face sensor's error (measured - simulated) of every sample as faint
    dots (rasterized) and its RMS in 2 K bins of the face sensors' mean as a line
    with markers; a vertical line marks 35 degC and the grey band the
    paper's +-0.5 K claim.

    Parameters
    ----------
    exp : Experiment
        The measured run (SI).
    sims : dict of str to Simulation
        Model label -> simulation of ``exp`` (draw 0 used), e.g.
        ``{"R, S constant at 35 °C": sim_c, "linear laws": sim_l}``.
    fig : matplotlib.figure.Figure, optional
        An empty figure to draw into; a new one (10 x 5 in) if absent.

    Returns
    -------
    matplotlib.figure.Figure
        One axes; the binned RMS lines carry ``gid="rms:<label>"``.
    """
    if not sims:
        raise ValueError("sims is empty: give at least one model's simulation")
    fig = _empty_figure(fig, (10.0, 5.0))
    ax = fig.add_subplot()
    hot, cold = face
    h_name, c_name = hot.removesuffix("_C"), cold.removesuffix("_C")
    x = 0.5 * (exp.channel(hot) + exp.channel(cold)) - KELVIN
    lo = np.floor(x.min() / BIN_WIDTH_K) * BIN_WIDTH_K
    edges = np.arange(lo, x.max() + BIN_WIDTH_K, BIN_WIDTH_K)
    if len(edges) < 2:
        edges = np.array([lo, lo + BIN_WIDTH_K])
    ax.axhspan(-ACCURACY_BAND_K, ACCURACY_BAND_K, color="0.9", zorder=0)
    ax.axhline(0.0, color="0.5", lw=0.6, zorder=0)
    handles = []
    for i, (label, sim) in enumerate(sims.items()):
        color = _module_color(i)
        r = exp.channel(cold) - _sim_sensors(exp, sim)[sim.channels.index(cold)]
        ax.scatter(x, r, s=4, alpha=0.15, color=color, lw=0, rasterized=True, zorder=1)
        centres, rms = _binned_rms(x, r, edges)
        ax.plot(centres, rms, color=color, lw=2.0, marker="o", ms=5, zorder=3, gid=f"rms:{label}")
        total = float(np.sqrt(np.mean(r**2)))
        handles.append(Line2D([], [], color=color, lw=2.0, marker="o", label=f"{label} (overall RMSE {total:.2f} K)"))
    ax.axvline(CONSTANT_MODEL_T_C, color="k", ls=":", lw=1.2, zorder=2)
    handles += [
        Line2D([], [], color="k", ls=":", lw=1.2, label=f"{CONSTANT_MODEL_T_C:g} °C (constant model's T)"),
        Line2D([], [], color="0.4", marker=".", ls="none", label=f"{c_name} error per sample"),
        Line2D([], [], color="0.4", marker="o", lw=2.0, label=f"RMS per {BIN_WIDTH_K:g} K bin"),
        Patch(facecolor="0.9", label=f"±{ACCURACY_BAND_K:g} K (paper's accuracy)"),
    ]
    # beside the axes: the dots fill the whole plane
    ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_xlabel(f"Mean sensor temperature ({h_name} + {c_name})/2 [°C]")
    ax.set_ylabel(f"{c_name} error, measured − simulated [K]")
    ax.set_title(f"Cold-side sensor ({c_name}) error vs temperature: {_run_name(exp)}")
    ax.grid(True, alpha=0.3)
    return fig


def _save_png(fig, path):
    """Render to memory, then write atomically (temp file in the folder + rename)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return atomic_write_bytes(path, buf.getvalue())


def save_identify_figures(results: Mapping[str, ModuleIdentification], batch: Batch, out_dir: Path | str) -> list[Path]:
    """Write the identification figures of a batch as PNG files.

    Files (``dpi`` 120), each written atomically:

    - ``identification_run.png`` (:func:`plot_identification_run`);
    - ``law_R.png``, ``law_S.png`` (:func:`plot_law`, with the batch average);
    - per module and validation run ``validation_<module>_<stem>_constant.png``
      (R, S constant at 35 degC, Fig. 8), ``..._linear.png`` (the laws,
      Fig. 9) and ``error_vs_tavg_<module>_<stem>.png``.

    Parameters
    ----------
    results : dict of str to ModuleIdentification
        :func:`tembayes.identify.pipeline.identify_batch` output.
    batch : tembayes.data.Batch
        The batch it was run on (for the measured experiments).
    out_dir : str or Path
        Created if missing; existing files of the same names are replaced.

    Returns
    -------
    list of Path
        The written files, in the order above.
    """
    from tembayes.identify.pipeline import batch_average  # the plots read results; only this helper is shared

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    missing = [mid for mid in results if mid not in batch.modules]
    if missing:
        raise ValueError(
            f"modules {missing} of the results are not in the batch {batch.path}; "
            "pass the batch the results were computed from"
        )
    written = [
        _save_png(
            plot_identification_run(
                {mid: batch.modules[mid].identification for mid in results}, face=batch.layout.face
            ),
            out / "identification_run.png",
        )
    ]
    average = batch_average(results)
    for which in ("R", "S"):
        written.append(_save_png(plot_law(results, which, average=average), out / f"law_{which}.png"))
    titles = {
        "constant": "R_m, S_m constant at 35 °C (paper Fig. 8)",
        "linear": "linear laws R_m(T), S_m(T) (paper Fig. 9)",
    }
    for mid, res in results.items():
        runs = {v.path.name: v for v in batch.modules[mid].validations}
        for fname, models in res.validation.items():
            if fname not in runs:
                raise ValueError(f"{mid}: validation run {fname} is not in the batch ({sorted(runs)})")
            exp = runs[fname]
            stem = Path(fname).stem
            for model, title in titles.items():
                fig = plot_validation(exp, models[model]["simulation"], title=f"{mid} {fname}: {title}")
                written.append(_save_png(fig, out / f"validation_{mid}_{stem}_{model}.png"))
            sims = {
                f"R, S constant at {CONSTANT_MODEL_T_C:g} °C": models["constant"]["simulation"],
                "linear laws": models["linear"]["simulation"],
            }
            fig = plot_error_vs_tavg(exp, sims, face=batch.layout.face)
            written.append(_save_png(fig, out / f"error_vs_tavg_{mid}_{stem}.png"))
    return written
