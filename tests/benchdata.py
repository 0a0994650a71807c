"""Bench recordings the tests share."""

import numpy as np

from tembayes.bench import bench as B
from tembayes.bench import hifi
from tembayes.bench.protocols import validation_cycle
from tembayes.data import load_experiment
from tembayes.data.write import write_experiment_csv


def record_validation(truth_module, path, seed, hours=2.0, start="steady"):
    """A validation run (1 Hz) of a bench module with its true parameters, written to ``path`` and loaded.

    ``start="rest"``: the rig at rest and the current switched straight to the first level.
    """
    rng = np.random.default_rng(seed)
    proto = validation_cycle(rng, 6.4, duration=hours * 3600.0, rest=0.0 if start == "rest" else 300.0)
    exp = B.run_experiment(proto, truth_module, {}, rng, rate=1.0, rig=hifi.hifi_rig(), t0=123.4, start=start)
    write_experiment_csv(path, exp)
    return load_experiment(path)
