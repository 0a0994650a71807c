"""The virtual bench's higher-fidelity rig and module.

Where the calibration model (:data:`tembayes.physics.rigread.REFERENCE`) has two
nodes per steel block and a lumped module, the bench resolves:

- each steel block into 6 cells of 1.67 mm, so the sensors (2.5 mm from a
  face) sit at cell centres and the heat path from junction to sensor is a
  distributed one;
- the module into its alumina plates and ``n_leg`` leg cells, with Joule heat
  released along the legs at the local temperature's resistance, conduction
  along the legs, and (``thomson`` effect) Peltier heat at each junction's own
  Seebeck coefficient plus Thomson heat in the legs;
- the enclosure leak spread over the block sides, with the bottom block's
  tabs at its bottom cell.

It reuses the same compiled kernel: a leg chain is just a longer module chain.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tembayes.physics.rig import RigDescription, RigParameter, SensorDepth
from tembayes.physics.rigfile import CERAMIC, JUNCTION_SHARE
from tembayes.physics.rigread import REFERENCE

if TYPE_CHECKING:
    from collections.abc import Mapping

N_BLOCK_CELLS = 6
N_LEG_CELLS = 4

#: The reference rig's steel blocks (its file gives their lumped values).
K_STEEL = 16.2  # AISI 304 [W/(m K)]
AREA = 0.040 * 0.040  # block and module footprint [m^2]
RHO_C = 7900.0 * 500.0  # volumetric heat capacity of the steel [J/(m^3 K)]
#: Nominal depth of every sensor below its block's nearer face [m].
SENSOR_DEPTH = 2.5e-3
#: The reference rig's sensor depths (T1 and T4 held by a calibration, T2 and T3 sampled; drawn by the bench).
DEPTHS = tuple(p for p in REFERENCE.parameters if p.name.startswith("depth_"))

#: Bench rig parameters that the reference rig has too (same name, meaning
#: and documented range), so a calibration's rig posterior can be checked.
SHARED_WITH_REFERENCE = (
    "g_cooler",
    "g_paste_hot",
    "g_paste_cold",
    "c_plate_hot",
    "c_plate_cold",
    "c_legs",
    "leak_top",
    "leak_bottom",
    "g_ceramic",
    *(p.name for p in DEPTHS),
)

_DX = 0.010 / N_BLOCK_CELLS  # cell thickness [m]
_G_CELL = K_STEEL * AREA / _DX  # centre to centre [W/K]
_C_CELL = RHO_C * AREA * _DX  # [J/K]

#: Bench rig parameters: the reference rig's physical ones, with the steel
#: resolved into cells.
HIFI_PARAMETERS = tuple(p for p in REFERENCE.parameters if p.name in SHARED_WITH_REFERENCE) + (
    RigParameter("c_cell", _C_CELL, 0.97 * _C_CELL, 1.03 * _C_CELL, "J/K", "one block cell"),
    RigParameter("g_cell", _G_CELL, 0.95 * _G_CELL, 1.05 * _G_CELL, "W/K", "steel, cell centre to centre"),
    RigParameter("g_half_cell", 2 * _G_CELL, 1.9 * _G_CELL, 2.1 * _G_CELL, "W/K", "steel, face to cell centre"),
)


def hifi_rig(n_leg: int = N_LEG_CELLS, layers: bool = False) -> RigDescription:
    """The bench's higher-fidelity description of the reference rig.

    With ``layers`` (the ``full`` model form's structure) each plate is two
    layers, alumina and the junctions' copper, joined by ``g_ceramic``;
    without, one node as in the paper.
    """
    nb = N_BLOCK_CELLS
    top = [f"top_{i + 1}" for i in range(nb)]  # top_1 at the water cooler
    bottom = [f"bottom_{i + 1}" for i in range(nb)]  # bottom_1 at the module
    legs = [f"leg_{i + 1}" for i in range(n_leg)]  # leg_1 at the hot plate
    share, rest = repr(JUNCTION_SHARE), repr(1.0 - JUNCTION_SHARE)
    nodes = [(n, "c_cell") for n in top]
    nodes += (
        [("hot_ceramic", f"{rest}*c_plate_hot"), ("hot_plate", f"{share}*c_plate_hot")]
        if layers
        else [("hot_plate", "c_plate_hot")]
    )
    nodes += [(n, f"{1.0 / n_leg!r}*c_legs") for n in legs]
    nodes += (
        [("cold_plate", f"{share}*c_plate_cold"), ("cold_ceramic", f"{rest}*c_plate_cold")]
        if layers
        else [("cold_plate", "c_plate_cold")]
    )
    nodes += [(n, "c_cell") for n in bottom]
    half = ["2.0*g_ceramic"] if layers else []
    links = [("water", top[0], ["g_cooler", "g_half_cell"])]
    links += [(a, b, "g_cell") for a, b in zip(top[:-1], top[1:])]
    links += [(top[-1], "hot_ceramic" if layers else "hot_plate", ["g_half_cell", "g_paste_hot"] + half)]
    links += [("cold_ceramic" if layers else "cold_plate", bottom[0], half + ["g_paste_cold", "g_half_cell"])]
    if layers:
        links += [("hot_ceramic", "hot_plate", half[0]), ("cold_plate", "cold_ceramic", half[0])]
    links += [(a, b, "g_cell") for a, b in zip(bottom[:-1], bottom[1:])]
    links += [(n, "ambient", f"{1.0 / nb!r}*leak_top") for n in top]
    # half of the bottom leak through the side walls, half through the tabs
    links += [(n, "ambient", f"{0.5 / nb!r}*leak_bottom") for n in bottom]
    links += [(bottom[-1], "ambient", "0.5*leak_bottom")]
    return RigDescription(
        name=f"bench-hifi-{n_leg}" + ("-layers" if layers else ""),
        parameters=HIFI_PARAMETERS + ((CERAMIC,) if layers else ()),
        nodes=tuple(nodes),
        links=tuple(links),
        hot="hot_plate",
        cold="cold_plate",
        # 6 cells of 1.67 mm: centres 2, 5 are 2.5 mm from a face
        sensors={"T1_C": top[1], "T2_C": top[4], "T3_C": bottom[1], "T4_C": bottom[4]},
        legs=tuple(legs),
        faces=("hot_ceramic", "cold_ceramic") if layers else (),
        boundaries=REFERENCE.boundaries,
        depths={
            ch: SensorDepth(deeper, f"depth_{ch[:2]}", SENSOR_DEPTH, _DX)
            for ch, deeper in (("T1_C", top[2]), ("T2_C", top[3]), ("T3_C", bottom[2]), ("T4_C", bottom[3]))
        },
    )


def reference_equivalent(bench_values: Mapping[str, float]) -> dict[str, float]:
    """The reference rig's parameter values that correspond to bench rig values.

    Written to ``truth.json`` so that a calibration's rig posterior can be
    checked.  A bench that draws its steel (``c_cell``, ``g_cell``) gives the
    reference rig's steel at the same ratio to nominal (one material, one
    heat capacity and one conductivity), and its bottom leak's even split
    between side walls and tabs is ``tab_share`` 0.5.
    """
    out = {k: bench_values[k] for k in SHARED_WITH_REFERENCE if k in bench_values}
    if "c_cell" in bench_values and "g_cell" in bench_values:
        out["c_half_block"] = REFERENCE.parameter("c_half_block").nominal * bench_values["c_cell"] / _C_CELL
        for k in ("g_steel_half", "g_steel_quarter"):
            out[k] = REFERENCE.parameter(k).nominal * bench_values["g_cell"] / _G_CELL
        out["tab_share"] = 0.5
    return out
