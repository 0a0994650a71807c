"""The virtual bench on any rig file: the rig at a finer resolution than the calibration's.

The reference rig has benches of its own (:mod:`tembayes.bench.hifi`, its
model's structure; :mod:`tembayes.bench.outside`, a rig the model does not
contain).  Any other rig file is simulated here: its blocks split into
:data:`BENCH_SPLIT` cells per cell of the file (the calibration splits
them into 3), the module's legs in :data:`BENCH_LEG_CELLS` cells (the
calibration's 4), the plates layered (copper and alumina), with the physics
of the calibration model's default form (Thomson heat, a temperature slope of
K, a sensor response time).  Its structure is the rig file's: like the
reference rig's standard bench it proves that every stage runs on the rig
and measures coverage where the model's structure holds, not how far a real
rig departs from the file.

Rig values: each parameter drawn once for the batch within its documented
range (the rig is one rig), except the module and its mounting
(:func:`mounting_parameters`), drawn again for every module.

:func:`outside_bench_rig` is the out-of-model bench on any rig file
(``--fidelity high``): on top of that network it adds what a real rig has
and no rig file describes.  The reference rig's out-of-model bench
(:mod:`tembayes.bench.outside`) has the bodies, edge leaks and re-mounting
too, but no sensor leads, and draws its edge leak once per batch:

- **sensor bodies**: each sensor a node of its own (``c_sensor``) in contact
  with what it reads (``g_sensor``, a time constant near 1 s); in a block,
  also with the next cell deeper in (a share ``v_<column>`` of its contact,
  drawn per rig: the hole is not exactly at the cell's centre);
- **sensor leads**: each body conducts to the room through its leads
  (``g_lead``, 0.02-0.7 % of its contact: thin leads partly anchored on the
  rig): a sensor reads a little towards the room, more the farther its node
  is from the room's temperature;
- **module edges**: each module face leaks to the room (``leak_module``);
- **re-mounting**: the links to the rig's boundaries vary from one mounting
  to the next (:func:`remount_spreads`);
- the physics of the reference out-of-model bench (Thomson heat, a
  temperature slope of K) and its slow sensor noise (the caller's).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tembayes.physics.layout import LEAK_MAX_W_PER_K
from tembayes.physics.rig import RigDescription, RigParameter
from tembayes.physics.rigfile import expression_names

if TYPE_CHECKING:
    from tembayes.physics.rigfile import RigFile

#: Cells per cell of a rig file's blocks on the bench (odd: a cell's centre stays a node).
BENCH_SPLIT = 9
#: The module's leg cells on the bench.
BENCH_LEG_CELLS = 8


def bench_rig(rig_file: RigFile, *, layers: bool = True) -> RigDescription:
    """The rig file's network at the bench's resolution."""
    return rig_file.build(leg_cells=BENCH_LEG_CELLS, split=BENCH_SPLIT, layers=layers)


#: What the out-of-model bench adds to any rig (:func:`outside_bench_rig`); the bodies and edge leaks
#: as the reference rig's out-of-model bench has them (:data:`tembayes.bench.outside.OUTSIDE_PARAMETERS`).
OUTSIDE_ANY_PARAMETERS = (
    RigParameter("c_sensor", 0.01, 0.005, 0.02, "J/K", "a sensor body"),
    RigParameter("g_sensor", 0.012, 0.006, 0.03, "W/K", "a sensor's contact with what it reads"),
    RigParameter("g_lead", 1.5e-5, 5e-6, 4e-5, "W/K", "a sensor's leads to the room"),
    RigParameter("leak_module", 0.004, 0.002, 0.008, "W/K", "one module plate's edge to the air"),
)
#: Largest share of a block sensor's contact with the next cell deeper in.
DEPTH_SHARE_MAX = 0.5
#: Re-mounting spread (lognormal sd) of a link to a boundary: a main heat path, a leak.
REMOUNT_MAIN_SD, REMOUNT_LEAK_SD = 0.03, 0.1


def outside_bench_rig(rig: RigDescription) -> RigDescription:
    """``rig`` (the bench's network, :func:`bench_rig`) with sensor bodies, leads and module edge leaks.

    Block sensors lose their depth interpolation (and its depth parameters): a
    contact share with the next cell (``v_<column>``, held over
    ``[0, DEPTH_SHARE_MAX]``) replaces it.  The rig file's lead shares and
    sensors' own response times (and their parameters) give way to the
    bodies' own leads and heat capacities.
    """
    room = rig.layout.leak_boundary
    dropped = {d.parameter for d in rig.depths.values()} | rig.lead_parameters | rig.lag_parameters
    nodes, links, sensors, shares = list(rig.nodes), list(rig.links), {}, []
    for column, node in rig.sensors.items():
        body = f"sensor_{column}"
        nodes.append((body, "c_sensor"))
        links += [(body, node, "g_sensor"), (body, room, "g_lead")]
        if column in rig.depths:
            share = RigParameter(
                f"v_{column}", 0.25, 0.0, DEPTH_SHARE_MAX, "1", f"{column}'s contact with the next cell", True
            )
            shares.append(share)
            links.append((body, rig.depths[column].toward, f"g_sensor*{share.name}"))
        sensors[column] = body
    links += [(face, room, "leak_module") for face in rig.faces or rig.module_faces]
    return RigDescription(
        name=rig.name + "-outside",
        parameters=(*(p for p in rig.parameters if p.name not in dropped), *OUTSIDE_ANY_PARAMETERS, *shares),
        nodes=tuple(nodes),
        links=tuple(links),
        hot=rig.hot,
        cold=rig.cold,
        sensors=sensors,
        legs=rig.legs,
        faces=rig.faces,
        physics=dict(rig.physics),
        boundaries=dict(rig.boundaries),
    )


def remount_spreads(rig: RigDescription, shared) -> dict[str, float]:
    """Lognormal sd of each of the ``shared`` conductances only links to a boundary use: re-made at every mounting.

    :data:`REMOUNT_LEAK_SD` for a leak (a link below :data:`~tembayes.physics.layout.LEAK_MAX_W_PER_K`
    at nominal values), :data:`REMOUNT_MAIN_SD` for a main heat path.  Not the sensors' own
    (:data:`OUTSIDE_ANY_PARAMETERS`) and not the shares (unit ``1``).
    """
    nominal = {p.name: p.nominal for p in rig.parameters}
    fixed = {p.name for p in rig.parameters if p.unit == "1"} | {p.name for p in OUTSIDE_ANY_PARAMETERS}
    at_boundary, skip = [], set(fixed)
    for a, b, expr in rig.links:
        if a in rig.boundaries or b in rig.boundaries:
            at_boundary.append(expr)
        else:
            skip.update(expression_names(expr))  # also inside the rig: not re-made at a mounting
    out = {}
    for expr in at_boundary:
        sd = REMOUNT_LEAK_SD if rig.evaluate(expr, nominal) < LEAK_MAX_W_PER_K else REMOUNT_MAIN_SD
        for name in expression_names(expr):
            if name in shared and name not in skip:
                out[name] = max(out.get(name, 0.0), sd)
    return out


def mounting_parameters(rig: RigDescription) -> frozenset[str]:
    """Parameters of the module and its mounting: drawn again for every module.

    The module's own capacitances and layers (its plates, legs, alumina) and
    the conductances between its faces and the rig that no other link uses.
    """
    own = {*rig.tem_chain, *rig.module_faces}

    module, elsewhere = set(), set()
    for a, b, expr in rig.links:
        (module if a in own or b in own else elsewhere).update(expression_names(expr))
    module |= {n for node, expr in rig.nodes if node in own for n in expression_names(expr)}
    return frozenset((module - elsewhere) & set(rig.parameter_names))


def draw_rig_values(rng: np.random.Generator, parameters: tuple[RigParameter, ...], names) -> dict[str, float]:
    """Values for ``names`` of ``parameters``: a held one uniform over its range, the others truncated normal.

    The truncated normal has the range as +-3 sd about the nominal value (as
    the reference benches draw theirs).
    """
    by_name = {p.name: p for p in parameters}
    out = {}
    for name in names:
        p = by_name[name]
        if p.held:
            out[name] = float(rng.uniform(p.low, p.high))
            continue
        sd = (p.high - p.low) / 6.0
        while True:
            v = rng.normal(p.nominal, sd)
            if p.low <= v <= p.high:
                out[name] = float(v)
                break
    return out
