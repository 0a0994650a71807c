"""Physics: module laws, rig network, effect catalogue and the batched simulator."""

from tembayes.physics.effects import CATALOGUE, parse_effects
from tembayes.physics.rig import PRESETS, REFERENCE, RigDescription, RigParameter, rig_from_config
from tembayes.physics.simulate import Inputs, Simulation, simulate

__all__ = [
    "CATALOGUE",
    "PRESETS",
    "REFERENCE",
    "Inputs",
    "RigDescription",
    "RigParameter",
    "Simulation",
    "parse_effects",
    "rig_from_config",
    "simulate",
]
