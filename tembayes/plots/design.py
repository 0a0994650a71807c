"""A design drawn: the current program beside the reference's, and the expected widths against test time.

Reads a :class:`~tembayes.design.search.Design` only.
"""

from __future__ import annotations

import io
from itertools import cycle
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

from tembayes.bench.protocols import REFERENCE_IMAX
from tembayes.constants import KELVIN, MODULE_PARAMETERS
from tembayes.data.write import atomic_write_bytes
from tembayes.report.outliers import short

if TYPE_CHECKING:
    from pathlib import Path

    from tembayes.design.search import Design

__all__ = ["plot_design", "save_design_figure"]

DPI = 120


def _held(ax, protocol, values, **kw):
    """``values`` (one per hold) as steps against time [h], the last held to the end."""
    ax.step(protocol.edges / 3600.0, np.concatenate([values, values[-1:]]), where="post", **kw)


def plot_design(design: Design) -> Figure:
    """Left: the designed and the reference current programs; right: expected sd (%) per law against test time."""
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    a, b = fig.subplots(1, 2)
    ref, best = design.reference, design.best
    _held(
        a,
        ref.protocol,
        ref.protocol.levels,
        color="0.6",
        label=f"reference ({ref.duration_s / 3600:.2f} h, {ref.rate_Hz:g} Hz)",
    )
    _held(
        a,
        best.protocol,
        best.protocol.levels,
        color="C3",
        lw=2,
        label=f"design ({best.duration_s / 3600:.2f} h, {best.rate_Hz:g} Hz)",
    )
    a.set(xlabel="time [h]", ylabel="current [A]", title="identification program")
    a.legend(loc="upper right", fontsize=8)
    if best.protocol.setpoints is not None:  # plates that hold both faces: their temperature is programmed too
        c = a.twinx()
        _held(c, best.protocol, best.protocol.setpoints - KELVIN, color="0.2", ls=":", lw=1.5)
        c.set_ylabel("design's plate setpoint [°C] (dotted)")
    # the rig's rate filled; the shortest staircase at the slower rates tried, hollow; beyond the temperature
    # limits, a cross; each span of currents its own marker
    inside = [e for e in design.evaluated if e.within(design.limits_K)]
    rig = [e for e in inside if e.rate_Hz == ref.rate_Hz]
    slower = [e for e in inside if e.rate_Hz != ref.rate_Hz]
    outside = [e for e in design.evaluated if not e.within(design.limits_K)]
    spans = sorted({(e.top_A, e.bottom_A) for e in design.evaluated}, key=lambda t: t[0] - t[1])
    marker = dict(zip(spans, cycle("v^osD")))
    targets = {t.parameter: t for t in design.targets}
    for k, p in enumerate(MODULE_PARAMETERS):
        for group, face in ((rig, f"C{k}"), (slower, "none")):
            for e in group:
                shape = marker[(e.top_A, e.bottom_A)]
                b.plot(e.duration_s / 3600, 100 * e.sd_rel()[p], shape, ms=4, color=f"C{k}", mfc=face, alpha=0.7)
        for e in outside:
            b.plot(e.duration_s / 3600, 100 * e.sd_rel()[p], "x", ms=4, color=f"C{k}", alpha=0.35)
        b.plot([], [], "-", lw=3, color=f"C{k}", label=short(p))
        t = targets.get(p)
        if t is not None and t.rel:
            b.axhline(100 * t.value, color=f"C{k}", ls="--", lw=1)
        b.plot(design.best.duration_s / 3600, 100 * design.best.sd_rel()[p], "*", ms=12, color=f"C{k}", mec="k")
    b.axvline(design.reference.duration_s / 3600, color="0.6", lw=1)
    b.set(
        xlabel="test time [h]",
        ylabel="expected posterior sd [%]",
        yscale="log",
        title=f"candidates at {ref.rate_Hz:g} Hz; hollow: slower rates; x: too hot or cold; star: the design",
    )
    b.title.set_fontsize(9)
    for turns, m in marker.items():
        b.plot([], [], m, ms=5, color="0.4", mfc="none", label=f"{turns[0]:+g} / {turns[1]:+g} A")
    b.legend(
        fontsize=7,
        ncol=5,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.16),
        title=f"laws; markers: turning levels (for a {REFERENCE_IMAX:g} A module)",
        title_fontsize=7,
    )
    return fig


def save_design_figure(design: Design, path: Path) -> Path:
    """Write :func:`plot_design` as a PNG, atomically."""
    buf = io.BytesIO()
    plot_design(design).savefig(buf, format="png", dpi=DPI)
    return atomic_write_bytes(path, buf.getvalue())
