"""Stage 5 -- uncertainty inputs for observer design (``tembayes export``).

- :mod:`~tembayes.export.coverage`: the calibrated range, the default operating points;
- :mod:`~tembayes.export.linearise`: the rig linearised at an operating point;
- :mod:`~tembayes.export.observer`: moments, noise and linear models of a run;
- :mod:`~tembayes.export.schema`: every field of the file, its shape and unit;
- :mod:`~tembayes.export.formats`: JSON, NPZ and MAT.
"""
