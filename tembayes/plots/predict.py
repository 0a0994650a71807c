"""Figures of a posterior-predictive (``tembayes predict``).

The paper's Figures 8-9 with credible bands.

They read :class:`~tembayes.predict.predictive.Prediction` objects only.
Temperatures in degC, errors in K (= degC differences), voltage in V.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from tembayes.constants import KELVIN
from tembayes.data.write import atomic_write_bytes
from tembayes.plots.identify import SENSOR_COLORS

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tembayes.predict.predictive import Prediction, PredictResult

#: Band shades, widest first (95, 90, 50 %).
_BAND_ALPHA = {95: 0.18, 90: 0.3, 50: 0.55}
#: The paper's stated accuracy of its validation [K].
PAPER_ACCURACY_K = 0.5
DPI = 120


def _scale(ch):
    """(offset, factor, unit) to display a channel: degC for sensors, V."""
    return (KELVIN, 1.0, "°C") if ch != "voltage_V" else (0.0, 1.0, "V")


def _color(pred, ch):
    if ch == "voltage_V":
        return "C2"
    return SENSOR_COLORS[pred.channels.index(ch) % len(SENSOR_COLORS)]


def _title(pred):
    laws = "R, S linear in T̄" if pred.laws == "linear" else "R, S constant at 35 °C"
    return f"{Path(pred.source).name} — {pred.label}, {laws} ({pred.n_draws} posterior draws)"


def plot_prediction(pred: Prediction, *, fig: Figure | None = None) -> Figure:
    """Measured vs predicted channels with the 50/90/95 % bands (paper Fig. 9 with bands).

    One panel per channel (the rig's sensors, the voltage) plus the current on top.
    """
    fig = fig or Figure(figsize=(11.0, 12.0), layout="constrained")
    axes = fig.subplots(len(pred.channels) + 1, 1, sharex=True, height_ratios=[0.6] + [1.0] * len(pred.channels))
    t = (pred.time - pred.time[0]) / 3600.0
    axes[0].plot(t, pred.current, color="0.3", lw=0.8)
    axes[0].set_ylabel("current [A]")
    axes[0].grid(True, alpha=0.3)
    cov = {lv: pred.coverage(lv) for lv in pred.bands}
    for c, (ax, ch) in enumerate(zip(axes[1:], pred.channels)):
        off, fac, unit = _scale(ch)
        color = _color(pred, ch)
        for lv in sorted(pred.bands, reverse=True):
            lo, hi = pred.bands[lv]
            ax.fill_between(
                t,
                (lo[c] - off) * fac,
                (hi[c] - off) * fac,
                color=color,
                alpha=_BAND_ALPHA.get(lv, 0.3),
                lw=0,
                gid=f"band{lv}:{ch}",
            )
        ax.plot(t, (pred.measured[c] - off) * fac, color="k", lw=0.6, gid=f"measured:{ch}")
        ax.plot(t, (pred.median[c] - off) * fac, color=color, lw=0.8, ls="--", gid=f"median:{ch}")
        ax.set_ylabel(f"{pred.labels.get(ch, ch)} [{unit}]", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.set_title(
            "band coverage " + ", ".join(f"{lv} %: {100 * cov[lv][c]:.0f} %" for lv in sorted(pred.bands)),
            loc="right",
            fontsize=7,
        )
    handles = [
        Line2D([], [], color="k", lw=0.8, label="measured"),
        Line2D([], [], color="0.4", lw=0.8, ls="--", label="predictive median"),
    ]
    handles += [
        Patch(facecolor="0.4", alpha=_BAND_ALPHA.get(lv, 0.3), label=f"{lv} % band")
        for lv in sorted(pred.bands, reverse=True)
    ]
    axes[0].legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[-1].set_xlabel("time since start of run [h]")
    fig.suptitle(_title(pred))
    return fig


def plot_residuals(pred: Prediction, *, fig: Figure | None = None) -> Figure:
    """Measured minus predictive mean, with the bands centred the same way (paper Fig. 9, bottom)."""
    fig = fig or Figure(figsize=(11.0, 10.0), layout="constrained")
    axes = fig.subplots(len(pred.channels), 1, sharex=True)
    t = (pred.time - pred.time[0]) / 3600.0
    m = pred.metrics()
    for c, (ax, ch) in enumerate(zip(axes, pred.channels)):
        fac, unit = (1e3, "mV") if ch == "voltage_V" else (1.0, "K")
        color = _color(pred, ch)
        for lv in sorted(pred.bands, reverse=True):
            lo, hi = pred.bands[lv]
            ax.fill_between(
                t,
                (lo[c] - pred.mean[c]) * fac,
                (hi[c] - pred.mean[c]) * fac,
                color=color,
                alpha=_BAND_ALPHA.get(lv, 0.3),
                lw=0,
                gid=f"band{lv}:{ch}",
            )
        ax.plot(t, pred.residual[c] * fac, color="k", lw=0.5, gid=f"residual:{ch}")
        ax.axhline(0.0, color="0.5", lw=0.6)
        ax.set_ylabel(f"{ch.split('_')[0]} error [{unit}]", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.set_title(
            f"RMSE {m[ch]['rmse'] * fac:.3g} {unit}, max {m[ch]['max_abs'] * fac:.3g} {unit}, "
            f"90 % band coverage {100 * m[ch]['coverage90']:.0f} %",
            loc="right",
            fontsize=7,
        )
    axes[-1].set_xlabel("time since start of run [h]")
    fig.suptitle("Measured − predictive mean, with the predictive bands: " + _title(pred))
    return fig


def plot_error_vs_tavg(preds: Mapping[str, Prediction], *, fig: Figure | None = None) -> Figure:
    """RMSE against T-bar for several predictions (the paper's constant-vs-linear point).

    Parameters
    ----------
    preds : dict
        Label -> :class:`Prediction` of the same experiment.
    """
    fig = fig or Figure(figsize=(11.0, 4.5), layout="constrained")
    ax_t, ax_v = fig.subplots(1, 2)
    for i, (label, pred) in enumerate(preds.items()):
        rows = pred.by_tavg()
        x = np.array([0.5 * (r["Tavg_C_low"] + r["Tavg_C_high"]) for r in rows])
        for ch, ls in zip(pred.face[::-1], ("-", ":")):
            ax_t.plot(
                x,
                [r["rmse"][ch] for r in rows],
                color=f"C{i}",
                ls=ls,
                marker="o",
                ms=4,
                label=f"{label}: {ch.split('_')[0]}",
                gid=f"rms:{label}:{ch}",
            )
        ax_v.plot(
            x,
            [1e3 * r["rmse"]["voltage_V"] for r in rows],
            color=f"C{i}",
            marker="o",
            ms=4,
            label=label,
            gid=f"rms:{label}:voltage_V",
        )
    for ax in (ax_t, ax_v):
        ax.axvline(35.0, color="k", ls=":", lw=1.0)
        ax.set_xlabel("T̄ ≈ the face sensors' mean, measured [°C]")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    ax_t.axhline(PAPER_ACCURACY_K, color="0.5", lw=1.0, ls="--", label="paper's ±0.5 K")
    ax_t.legend(fontsize=8)
    ax_t.set_ylabel("RMSE per 5 K bin of T̄ [K]")
    ax_v.set_ylabel("voltage RMSE per 5 K bin [mV]")
    first = next(iter(preds.values()))
    fig.suptitle(f"Prediction error against T̄: {Path(first.source).name} — {first.label}")
    return fig


def _save_png(fig, path):
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def save_predict_figures(result: PredictResult, out_dir: Path | str) -> list[Path]:
    """Write the figure set of a :class:`~tembayes.predict.predictive.PredictResult`; returns the paths."""
    out = Path(out_dir)
    written = [
        _save_png(plot_prediction(result.linear), out / "prediction.png"),
        _save_png(plot_residuals(result.linear), out / "residuals.png"),
    ]
    if result.constant is not None:
        written.append(_save_png(plot_prediction(result.constant), out / "prediction_constant.png"))
        written.append(_save_png(plot_residuals(result.constant), out / "residuals_constant.png"))
        written.append(
            _save_png(
                plot_error_vs_tavg({"R, S linear in T̄": result.linear, "R, S constant at 35 °C": result.constant}),
                out / "error_vs_tavg.png",
            )
        )
    return written
