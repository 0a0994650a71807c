"""tembayes: Bayesian uncertainty quantification of thermoelectric-module parameters.

The pipeline, one sub-package per stage:

- :mod:`tembayes.data`     load and validate batch folders and experiment CSVs
- :mod:`tembayes.physics`  the module, the rig network, the effects, the simulator
- :mod:`tembayes.bench`    the virtual bench (synthetic batches with known truth)
"""

__version__ = "0.1.0"
