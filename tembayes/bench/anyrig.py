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
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tembayes.physics.rigfile import expression_names

if TYPE_CHECKING:
    from tembayes.physics.rig import RigDescription, RigParameter
    from tembayes.physics.rigfile import RigFile

#: Cells per cell of a rig file's blocks on the bench (odd: a cell's centre stays a node).
BENCH_SPLIT = 9
#: The module's leg cells on the bench.
BENCH_LEG_CELLS = 8


def bench_rig(rig_file: RigFile, *, layers: bool = True) -> RigDescription:
    """The rig file's network at the bench's resolution."""
    return rig_file.build(leg_cells=BENCH_LEG_CELLS, split=BENCH_SPLIT, layers=layers)


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
