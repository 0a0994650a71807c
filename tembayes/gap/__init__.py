"""Stage 5 -- the sim-to-real gap diagnosis (``tembayes gap``): where, which effect, how far."""
