"""Stage 5 -- the sim-to-real gap diagnosis (``tembayes gap``).

- :mod:`~tembayes.gap.where`: the gap map -- standardised held-out residuals per
  channel and operating regime, with a posterior-predictive significance;
  whiteness and cross-correlation with the input;
- :mod:`~tembayes.gap.which`: the screen -- the base model and every
  catalogue effect refitted on the identification run (posterior mode and
  Laplace evidence, the effect's size);
- :mod:`~tembayes.gap.conflicts`: rig parameters whose posterior lies outside
  their documented range (an effect absorbed by the base model) and the
  effects they point at;
- :mod:`~tembayes.gap.diagnose`: the whole diagnosis, step by step --
  :mod:`~tembayes.gap.baseline` (where the base model misses),
  :mod:`~tembayes.gap.screen` (the screen and the candidates chosen),
  :mod:`~tembayes.gap.candidates` (the workers' refits and recalibrations,
  run and raced by :mod:`~tembayes.gap.jobs`), :mod:`~tembayes.gap.evidence`
  (their held-out evidence) and :mod:`~tembayes.gap.ranking` (the ranking
  and the verdict); its result :mod:`~tembayes.gap.result` is ``gap.json``.

To add an effect, add it to :mod:`tembayes.physics.effects` (its parameters,
prior scale and hook); the screen, the recalibration and the benchmark pick
it up from the catalogue.  If a rig parameter's role can absorb it, add the
pair to :data:`tembayes.gap.conflicts.ROLE_SUSPECTS`.
"""

from tembayes.gap.diagnose import diagnose
from tembayes.gap.result import GapDiagnosis

__all__ = ["GapDiagnosis", "diagnose"]
