"""Stage 5 -- the sim-to-real gap diagnosis (``tembayes gap``; issue 6, in progress).

- :mod:`~tembayes.gap.where`: the gap map -- standardised held-out residuals per
  channel and operating regime, with a posterior-predictive significance;
  whiteness and cross-correlation with the input;
- :mod:`~tembayes.gap.which`: a linear-Gaussian screen of the effect catalogue
  (log Bayes factor of each effect's sensitivity pattern against the base
  parameters', with the effect's size);
- :mod:`~tembayes.gap.conflicts`: rig parameters whose posterior lies outside
  their documented range (an effect absorbed by the base model).

Still to come: recalibration of the strongest candidates with the effect
added, held-out evidence, the verdict, ``gap.json`` and the command.
"""
