"""The rig's network drawn: nodes with their capacities, links with their conductances, sensors, boundaries, module.

Reads a :class:`~tembayes.physics.rigsummary.RigSummary` only.  Nodes stand
in rows by how many links they are from the module: the hot side above it,
the cold side below; a boundary sits beyond the nodes it is linked to, or to
the right when it touches both sides.
"""

from __future__ import annotations

import io
from collections import deque
from typing import TYPE_CHECKING

from matplotlib.figure import Figure
from matplotlib.patches import FancyBboxPatch

from tembayes.data.write import atomic_write_bytes

if TYPE_CHECKING:
    from pathlib import Path

    from tembayes.physics.rigsummary import RigSummary

__all__ = ["plot_rig", "save_rig_figure"]

DPI = 120


def _rows(summary: RigSummary) -> dict:
    """Node -> signed row: +1 the hot node, -1 the cold node, farther nodes farther out."""
    rig = summary.rig
    nodes = [n for n, _ in summary.nodes]
    adj = {n: [] for n in nodes}
    for a, b, _ in summary.links:
        if a in adj and b in adj:
            adj[a].append(b)
            adj[b].append(a)
    dist = {}
    for start, sign in ((rig.hot, 1), (rig.cold, -1)):
        seen, todo = {start: 0}, deque([start])
        while todo:
            u = todo.popleft()
            for v in adj[u]:
                if v not in seen and v not in (rig.hot, rig.cold):
                    seen[v] = seen[u] + 1
                    todo.append(v)
        for n, d in seen.items():
            if n not in dist or d < abs(dist[n]) - 1:
                dist[n] = sign * (d + 1)
    return dist


def _positions(summary: RigSummary) -> dict:
    rows = _rows(summary)
    # a node joined only to boundaries (not to the module) stands beside it
    rows.update({n: 0 for n, _ in summary.nodes if n not in rows})
    pos = {}
    for r in sorted(set(rows.values())):
        members = [n for n, _ in summary.nodes if rows.get(n) == r]
        for i, n in enumerate(members):
            pos[n] = (i - 0.5 * (len(members) - 1), float(r))
    right = max((x for x, _ in pos.values()), default=0.0) + 2.0
    for k, bnd in enumerate(summary.rig.boundaries):
        ys = [pos[a if b == bnd else b][1] for a, b, _ in summary.links if bnd in (a, b)]
        if ys and min(ys) > 0:
            pos[bnd] = (1.5 * k, max(ys) + 1.0)
        elif ys and max(ys) < 0:
            pos[bnd] = (1.5 * k, min(ys) - 1.0)
        else:
            pos[bnd] = (right + 1.5 * k, 0.0)
    return pos


def plot_rig(summary: RigSummary) -> Figure:
    """The network drawing (see the module docstring)."""
    rig = summary.rig
    pos = _positions(summary)
    ys = [y for _, y in pos.values()]
    fig = Figure(figsize=(10, 1.2 * (max(ys) - min(ys)) + 3.5))
    ax = fig.add_subplot()
    parallel = {}  # links between the same two ends are drawn once, their conductances listed
    for a, b, g in summary.links:
        parallel.setdefault(frozenset((a, b)), []).append(g)
    for ends, gs in parallel.items():
        (xa, ya), (xb, yb) = (pos[e] for e in sorted(ends))
        ax.plot([xa, xb], [ya, yb], color="0.6", lw=1, zorder=1)
        label = " + ".join(f"{g:.3g}" for g in gs) + " W/K"
        ax.text(
            0.5 * (xa + xb),
            0.5 * (ya + yb),
            label,
            fontsize=7,
            color="0.3",
            ha="center",
            va="center",
            bbox={"fc": "white", "ec": "none", "pad": 0.5},
            zorder=2,
        )
    (xh, yh), (xc, yc) = pos[rig.hot], pos[rig.cold]
    ax.add_patch(
        FancyBboxPatch(
            (min(xh, xc) - 0.9, yc + 0.25),
            abs(xh - xc) + 1.8,
            yh - yc - 0.5,
            boxstyle="round,pad=0.02",
            fc="#fde2c4",
            ec="#c76b00",
            zorder=1,
        )
    )
    ax.text(
        0.5 * (xh + xc),
        0.5 * (yh + yc),
        f"module: legs (K {summary.module_k:g} W/K assumed, Joule, Peltier)",
        ha="center",
        va="center",
        fontsize=8,
        color="#7a4000",
        zorder=3,
    )
    for n, c in summary.nodes:
        _label(ax, pos[n], f"{n}\n{c:.3g} J/K", 7, {"boxstyle": "round,pad=0.4", "fc": "#cfe3f5", "ec": "#1f5f99"})
    for bnd, col in rig.boundaries.items():
        _label(ax, pos[bnd], f"{bnd}\n({col})", 8, {"boxstyle": "square,pad=0.5", "fc": "#e6e6e6", "ec": "0.3"})
    for col, spec in rig.sensors.items():
        x, y = pos[spec.node]
        ax.annotate(
            col,
            (x - 0.4, y),
            xytext=(x - 1.1, y),
            fontsize=8,
            color="#a01818",
            zorder=5,
            ha="right",
            va="center",
            arrowprops={"arrowstyle": "-|>", "color": "#a01818", "lw": 0.8},
        )
    (s1, t1), (s2, t2) = list(summary.hold_times.items())[:2]
    taus = ", ".join(f"{t:.0f}" for t in summary.time_constants[:3])
    ax.set_title(
        f"rig '{rig.name}' (sensors in red)\nslowest time constants {taus} s; a step's hold for every sensor "
        f"within {100 * s1:g} % of its move: {t1 / 60:.1f} min ({100 * s2:g} %: {t2 / 60:.1f} min)",
        fontsize=9,
    )
    ax.set_axis_off()
    xs = [x for x, _ in pos.values()]
    ax.set_xlim(min(xs) - 2.0, max(xs) + 1.0)
    ax.set_ylim(min(ys) - 0.8, max(ys) + 0.8)
    fig.tight_layout()
    return fig


def _label(ax, xy, text, size, box):
    """A node's or boundary's boxed label at ``xy``."""
    ax.text(*xy, text, ha="center", va="center", fontsize=size, zorder=4, bbox=box)


def save_rig_figure(summary: RigSummary, path: Path) -> Path:
    """Write :func:`plot_rig` as a PNG, atomically."""
    buf = io.BytesIO()
    plot_rig(summary).savefig(buf, format="png", dpi=DPI)
    return atomic_write_bytes(path, buf.getvalue())
