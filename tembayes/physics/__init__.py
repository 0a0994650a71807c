"""Physics: module laws, rig network, effect catalogue and the batched simulator."""

from tembayes.physics.effects import CATALOGUE, parse_effects
from tembayes.physics.rig import RigDescription, RigParameter
from tembayes.physics.rigread import REFERENCE, SHIPPED, read_rig_file, rig_from_config, shipped_rig
from tembayes.physics.simulate import Inputs, Simulation, simulate

__all__ = [
    "CATALOGUE",
    "REFERENCE",
    "SHIPPED",
    "Inputs",
    "RigDescription",
    "RigParameter",
    "Simulation",
    "parse_effects",
    "read_rig_file",
    "rig_from_config",
    "shipped_rig",
    "simulate",
]
