"""Figures of the gap diagnosis: the gap map as a heat map, residual patterns.

They read :class:`~tembayes.gap.where.GapMap`,
:class:`~tembayes.predict.predictive.Prediction` and
:class:`~tembayes.gap.result.GapDiagnosis` objects only.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from tembayes.constants import KELVIN
from tembayes.gap.ranking import RECALIBRATED

if TYPE_CHECKING:
    from tembayes.gap.result import GapDiagnosis
    from tembayes.gap.where import GapMap
    from tembayes.predict.predictive import Prediction


def plot_gap_map(gmap: GapMap, *, fig: Figure | None = None, alpha: float = 0.05) -> Figure:
    """Heat map of the score (RMS standardised residual) per channel and regime.

    1 means the measurement scatters as the predictive band says; cells that
    are significant after Bonferroni over all cells carry a star.
    """
    channels = list(gmap.channels)
    regimes = []
    for c in gmap.cells:
        if (c["family"], c["regime"]) not in regimes:
            regimes.append((c["family"], c["regime"]))
    S = np.full((len(channels), len(regimes)), np.nan)
    sig = {(c["channel"], c["regime"]) for c in gmap.significant(alpha)}
    for c in gmap.cells:
        S[channels.index(c["channel"]), regimes.index((c["family"], c["regime"]))] = c["score"]
    fig = fig or Figure(figsize=(max(7.0, 0.55 * len(regimes) + 3.0), 4.2), layout="constrained")
    ax = fig.add_subplot()
    im = ax.imshow(S, cmap="magma_r", norm=LogNorm(vmin=0.7, vmax=max(5.0, np.nanmax(S))), aspect="auto")
    for i, ch in enumerate(channels):
        for j, (_, reg) in enumerate(regimes):
            if np.isfinite(S[i, j]):
                ax.text(
                    j,
                    i,
                    f"{S[i, j]:.1f}" + ("*" if (ch, reg) in sig else ""),
                    ha="center",
                    va="center",
                    fontsize=7,
                    color="white" if S[i, j] > 2.5 else "black",
                )
    ax.set_yticks(range(len(channels)), channels)
    ax.set_xticks(range(len(regimes)), [r for _, r in regimes], rotation=60, ha="right", fontsize=7)
    fig.colorbar(im, ax=ax, label="RMS standardised residual")
    ax.set_title(
        f"Gap map: {Path(gmap.source).name} (* significant, Bonferroni over {len(gmap.cells)} cells, "
        f"{gmap.n_replicates} replicates)",
        fontsize=9,
    )
    return fig


def plot_residual_patterns(pred: Prediction, *, fig: Figure | None = None) -> Figure:
    """Standardised residuals against T-bar and against time since the last step, per channel.

    The standardisation uses the predictive's 90 % band (half-width / 1.645).
    """
    lo, hi = pred.bands[90]
    z = (pred.measured - pred.mean) / np.maximum((hi - lo) / (2 * 1.645), 1e-12)
    fig = fig or Figure(figsize=(11.0, 4.5), layout="constrained")
    ax_t, ax_s = fig.subplots(1, 2, sharey=True)
    tc = pred.tavg - KELVIN
    edges_t = np.arange(np.floor(tc.min()), tc.max() + 2.0, 2.0)
    s = np.maximum(pred.since_step if pred.since_step is not None else pred.time - pred.time[0], 0.5)
    edges_s = np.geomspace(0.5, s.max() * 1.01, 25)
    for c, ch in enumerate(pred.channels):
        for ax, x, edges in ((ax_t, tc, edges_t), (ax_s, s, edges_s)):
            idx = np.digitize(x, edges) - 1
            cen, rms = [], []
            for b in range(len(edges) - 1):
                m = idx == b
                if m.sum() >= 20:
                    cen.append(0.5 * (edges[b] + edges[b + 1]))
                    rms.append(np.sqrt(np.mean(z[c, m] ** 2)))
            ax.plot(cen, rms, marker="o", ms=3, lw=1.2, label=ch, gid=f"rms:{ch}")
    for ax in (ax_t, ax_s):
        ax.axhline(1.0, color="0.4", ls="--", lw=1.0)
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    ax_s.set_xscale("log")
    ax_t.set_xlabel("T̄ ≈ the face sensors' mean [°C]")
    ax_s.set_xlabel("time since the last current step [s]")
    ax_t.set_ylabel("RMS standardised residual per bin")
    ax_t.legend(fontsize=8)
    fig.suptitle(f"Residual patterns: {Path(pred.source).name} — {pred.label}")
    return fig


def plot_ranking(diag: GapDiagnosis, *, fig: Figure | None = None) -> Figure:
    """The candidates: held-out evidence (with 2 se) and the gap before and after, best first.

    Parameters
    ----------
    diag : GapDiagnosis
    """
    fig = fig or Figure(figsize=(10, 3.8), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    rows = [r for r in diag.ranking if r.evidence is not None]
    names = [r.effect for r in rows][::-1]
    y = np.arange(len(names))
    if rows and rows[0].kind == RECALIBRATED:
        ev = np.array([r.evidence.value for r in rows][::-1])
        se = np.array([r.evidence.se for r in rows][::-1])
        # recalibrated on every module (blue, the best green); on the lead module only, or only
        # screened (its refit's Laplace posterior): grey
        colour = ["C2" if r.effect == diag.best else "C0" if r.kind == RECALIBRATED else "0.65" for r in rows][::-1]
        ax1.barh(y, ev, xerr=2 * se, color=colour)
        ax1.set_xlabel(
            "held-out ELPD difference to the base model [nats], ±2 se\n"
            "(grey: the lead module only, recalibrated or screened)"
        )
        ax1.set_xscale("symlog", linthresh=max(1.0, float(np.min(np.abs(se[se > 0])) if np.any(se > 0) else 1.0)))
        before = np.array([r.gaps.on()[0] for r in rows][::-1]) * 1e3
        after = np.array([r.gaps.on()[1] for r in rows][::-1]) * 1e3
        ax2.barh(y + 0.2, before, height=0.4, color="0.6", label="base model")
        ax2.barh(y - 0.2, after, height=0.4, color="C1", label="with the effect")
        ax2.set_xlabel("held-out gap (excess RMSE over the sensors) [mK]")
        ax2.legend(fontsize=8)
    else:
        for ax in (ax1, ax2):
            ax.axis("off")
        ax1.text(0.5, 0.5, f"{diag.verdict}: nothing recalibrated", ha="center", va="center", transform=ax1.transAxes)
    for ax in (ax1, ax2):
        ax.set_yticks(y, names if ax is ax1 else [""] * len(names))
        ax.grid(axis="x", alpha=0.3)
    fig.suptitle(f"verdict: {diag.verdict}" + (f" — best: {' ≈ '.join(diag.best_group)}" if diag.best else ""))
    return fig


def save_gap_figures(diag: GapDiagnosis, out_dir: Path | str) -> list[Path]:
    """Write the figure set of a :class:`~tembayes.gap.result.GapDiagnosis`; returns the paths.

    ``ranking.png``, and per module and held-out run ``gap_map_<module>_<run>.png``
    and ``residuals_<module>_<run>.png``.
    """
    from tembayes.plots.predict import _save_png

    out = Path(out_dir)
    written = [_save_png(plot_ranking(diag), out / "ranking.png")]
    for ev in diag.base.evals:
        tag = f"{ev.module_id}_{Path(ev.source).stem}"
        written.append(_save_png(plot_gap_map(ev.gap_map), out / f"gap_map_{tag}.png"))
        if ev.prediction is not None:
            written.append(_save_png(plot_residual_patterns(ev.prediction), out / f"residuals_{tag}.png"))
    return written
