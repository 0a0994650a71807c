"""The typical module and rig boundaries the physics tests share (SI)."""

# TEC1-12706 class (docs/data-format.md, 'The reference rig')
PAPER = {
    "R0_ohm": 1.75,
    "R1_ohm_per_K": 0.0087,
    "S0_V_per_K": 0.048,
    "S1_V_per_K2": 1e-4,
    "K_W_per_K": 0.54,
}
TW = 293.15  # water [K]
TA = 295.15  # ambient [K]
