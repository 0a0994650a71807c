"""The out-of-model bench: a rig and module the calibration model does not contain.

The standard bench (:mod:`tembayes.bench.hifi`) has the calibration model's
own structure at its default resolution, so it proves the code, not the
method.  This bench (``tembayes simulate --fidelity high``) adds what a real
rig has and the calibration model leaves out:

- **finer steel**: 18 cells of 0.56 mm per block (the model: 6), the leak
  spread over the block sides and the bottom block's tabs; the steel's heat
  capacity and conductivity drawn per rig within their documented ranges
  (+-3 %, +-5 %), since no rig's steel is exactly the handbook value;
- **the module's layers**: each face is an alumina plate (85 % of the plate's
  heat capacity) behind a copper/solder layer (15 %) where the junctions
  are, joined by the ceramic's own conductance (``g_ceramic``, ~50 W/K);
  the paste sits outside the ceramic; a small leak from each plate's edge to
  the air (``leak_module``);
- **legs** in 8 cells, with Joule heat at the local resistance, Peltier heat
  at each junction's own Seebeck coefficient and Thomson heat along them
  (the first law exact), and a thermal conductance that depends weakly on
  temperature (``K1_per_K``, drawn per module type);
- **sensor bodies**: each thermistor is a node of its own (``c_sensor``)
  glued into its hole with a contact conductance (``g_sensor``, a time
  constant near 1 s), at a depth off the nominal 2.5 mm by up to a quarter of a
  millimetre (drawn per rig, shared by the batch): it reads a blend of two
  steel cells;
- **re-mounting**: paste, plate and leg values per module, and the cooler
  clamp and enclosure leaks varying a little from one mounting to the next;
- **sensor noise** with a slow part: white 4 mK plus an Ornstein-Uhlenbeck
  component (1.5 mK, 20 s), as a bridge amplifier's drift gives.

The calibration model never sees these as parameters; a study that calibrates
on this bench measures the method on data its model cannot reproduce exactly.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tembayes.bench.hifi import AREA, K_STEEL, RHO_C
from tembayes.physics.rig import RigDescription, RigParameter
from tembayes.physics.rigread import REFERENCE

if TYPE_CHECKING:
    from collections.abc import Mapping

N_BLOCK_CELLS = 18
N_LEG_CELLS = 8
#: Cell whose centre sits 2.5 mm from a block face: (k + 0.5) * 10 mm / 18 = 2.5 mm.
SENSOR_CELL = 4

_DX = 0.010 / N_BLOCK_CELLS
_G_CELL = K_STEEL * AREA / _DX
_C_CELL = RHO_C * AREA * _DX

#: Parameters the reference rig has too (same name, meaning and documented range).
SHARED_WITH_REFERENCE = (
    "g_cooler",
    "g_paste_hot",
    "g_paste_cold",
    "c_plate_hot",
    "c_plate_cold",
    "c_legs",
    "leak_top",
    "leak_bottom",
)

OUTSIDE_PARAMETERS = (
    RigParameter("g_cooler", 12.5, 10.0, 15.0, "W/K", "water cooler to top block face"),
    RigParameter("g_paste_hot", 35.0, 20.0, 50.0, "W/K", "thermal paste, module hot face"),
    RigParameter("g_paste_cold", 35.0, 20.0, 50.0, "W/K", "thermal paste, module cold face"),
    RigParameter("c_plate_hot", 4.5, 4.0, 5.0, "J/K", "hot plate: alumina and copper"),
    RigParameter("c_plate_cold", 4.5, 4.0, 5.0, "J/K", "cold plate: alumina and copper"),
    RigParameter("c_legs", 1.25, 1.0, 1.5, "J/K", "all legs of the module together"),
    RigParameter("leak_top", 0.02, 0.01, 0.03, "W/K", "top block to ambient"),
    RigParameter("leak_bottom", 0.04, 0.02, 0.06, "W/K", "bottom block to ambient"),
    RigParameter("g_ceramic", 50.0, 35.0, 70.0, "W/K", "through an alumina plate to its copper"),
    RigParameter("leak_module", 0.004, 0.002, 0.008, "W/K", "one plate's edge to the air"),
    RigParameter("c_sensor", 0.01, 0.005, 0.02, "J/K", "a thermistor body"),
    RigParameter("g_sensor", 0.012, 0.006, 0.03, "W/K", "a thermistor's contact with its hole"),
    RigParameter("c_cell", _C_CELL, 0.97 * _C_CELL, 1.03 * _C_CELL, "J/K", "one steel cell"),
    RigParameter("g_cell", _G_CELL, 0.95 * _G_CELL, 1.05 * _G_CELL, "W/K", "steel, cell centre to centre"),
    *(
        RigParameter(f"w_{s}", 1.0, 0.0, 1.0, "1", f"{s}'s contact share with its own cell")
        for s in ("T1", "T2", "T3", "T4")
    ),
    *(
        RigParameter(f"v_{s}", 1e-9, 0.0, 1.0, "1", f"{s}'s contact share with the next cell")
        for s in ("T1", "T2", "T3", "T4")
    ),
)

#: How far a thermistor sits off its nominal depth, at most [m].
DEPTH_OFFSET_MAX = 0.25e-3
#: Share of a plate's heat capacity in its copper/solder layer.
COPPER_SHARE = 0.15


def outside_rig(depth_sides: Mapping[str, int] | None = None) -> RigDescription:
    """The out-of-model bench rig.

    Parameters
    ----------
    depth_sides : mapping of str to int, optional
        ``{"T1": +1, ...}``: which neighbouring cell (the next, +1, or the
        previous, -1, from the cooler's side) each sensor's depth offset
        points to; its size is in the ``w_``/``v_`` parameters.

    Returns
    -------
    RigDescription
    """
    nb, k = N_BLOCK_CELLS, SENSOR_CELL
    sides = {"T1": 1, "T2": 1, "T3": 1, "T4": 1, **(depth_sides or {})}
    top = [f"top_{i + 1}" for i in range(nb)]  # top_1 at the water cooler
    bottom = [f"bottom_{i + 1}" for i in range(nb)]  # bottom_1 at the module
    legs = [f"leg_{i + 1}" for i in range(N_LEG_CELLS)]
    sensor_cell = {"T1": (top, k), "T2": (top, nb - 1 - k), "T3": (bottom, k), "T4": (bottom, nb - 1 - k)}
    nodes = [(n, "c_cell") for n in top]
    nodes += [("hot_ceramic", f"{1 - COPPER_SHARE!r}*c_plate_hot"), ("hot_copper", f"{COPPER_SHARE!r}*c_plate_hot")]
    nodes += [(n, f"{1.0 / N_LEG_CELLS!r}*c_legs") for n in legs]
    nodes += [("cold_copper", f"{COPPER_SHARE!r}*c_plate_cold"), ("cold_ceramic", f"{1 - COPPER_SHARE!r}*c_plate_cold")]
    nodes += [(n, "c_cell") for n in bottom]
    nodes += [(f"sensor_{s}", "c_sensor") for s in sensor_cell]
    links = [("water", top[0], ["g_cooler", "2.0*g_cell"])]
    links += [(a, b, "g_cell") for a, b in zip(top[:-1], top[1:])]
    links += [(top[-1], "hot_ceramic", ["2.0*g_cell", "g_paste_hot", "2.0*g_ceramic"])]
    links += [("hot_ceramic", "hot_copper", "2.0*g_ceramic")]
    links += [("cold_copper", "cold_ceramic", "2.0*g_ceramic")]
    links += [("cold_ceramic", bottom[0], ["2.0*g_ceramic", "g_paste_cold", "2.0*g_cell"])]
    links += [(a, b, "g_cell") for a, b in zip(bottom[:-1], bottom[1:])]
    links += [(n, "ambient", f"{1.0 / nb!r}*leak_top") for n in top]
    links += [(n, "ambient", f"{0.5 / nb!r}*leak_bottom") for n in bottom]
    links += [(bottom[-1], "ambient", "0.5*leak_bottom")]
    links += [("hot_ceramic", "ambient", "leak_module"), ("cold_ceramic", "ambient", "leak_module")]
    for s, (block, i) in sensor_cell.items():
        j = i + sides[s]
        links += [(f"sensor_{s}", block[i], f"g_sensor*w_{s}"), (f"sensor_{s}", block[j], f"g_sensor*v_{s}")]
    return RigDescription(
        name="bench-outside",
        parameters=OUTSIDE_PARAMETERS,
        nodes=tuple(nodes),
        links=tuple(links),
        hot="hot_copper",
        cold="cold_copper",
        sensors={f"{s}_C": f"sensor_{s}" for s in sensor_cell},
        legs=tuple(legs),
        faces=("hot_ceramic", "cold_ceramic"),
        boundaries=REFERENCE.boundaries,
    )


def draw_sensor_depths(rng: np.random.Generator) -> tuple[dict[str, int], dict[str, float]]:
    """Per-rig sensor depth offsets: ``(depth_sides, {w_T1, v_T1, ...})``.

    A sensor ``d`` metres off its cell's centre (towards a neighbour) reads a
    blend of the two cells: contact share ``1 - d/dx`` with its own, ``d/dx``
    with the neighbour's.
    """
    sides, shares = {}, {}
    for s in ("T1", "T2", "T3", "T4"):
        d = rng.uniform(-DEPTH_OFFSET_MAX, DEPTH_OFFSET_MAX)
        sides[s] = 1 if d >= 0 else -1
        f = abs(d) / _DX
        shares[f"w_{s}"] = 1.0 - f
        shares[f"v_{s}"] = max(f, 1e-9)
    return sides, shares


def reference_equivalent(bench_values: Mapping[str, float]) -> dict[str, float]:
    """The reference rig's parameter values that correspond to bench rig values (for ``truth.json``)."""
    return {k: bench_values[k] for k in SHARED_WITH_REFERENCE if k in bench_values}


def ou_noise(rng: np.random.Generator, t: np.ndarray, sd: float, tau: float) -> np.ndarray:
    """An Ornstein-Uhlenbeck path of standard deviation ``sd`` and time constant ``tau`` [s] at times ``t``."""
    x = np.empty(len(t))
    x[0] = rng.normal(0.0, sd)
    a = np.exp(-np.diff(t) / tau)
    e = rng.standard_normal(len(t) - 1) * sd * np.sqrt(1.0 - a * a)
    for i in range(1, len(t)):
        x[i] = a[i - 1] * x[i - 1] + e[i - 1]
    return x
