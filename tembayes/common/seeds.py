"""Seed streams: every random number of a run derives from the run's seed and a label.

A label (a module id, a stage name) is hashed with CRC-32, so adding a module
or a stage never changes the streams of the others, and the same seed always
gives the same numbers.
"""

from __future__ import annotations

import zlib

import numpy as np


def label_key(label: str | int) -> int:
    """The integer key of a label: the CRC-32 of its text, or the integer itself."""
    if isinstance(label, (int, np.integer)):
        return int(label)
    return zlib.crc32(str(label).encode())


def stream(seed: int, *labels: str | int) -> np.random.Generator:
    """A ``numpy.random.Generator`` for the run seed and a path of labels.

    Parameters
    ----------
    seed : int
        The run's seed.
    *labels : str or int
        What the stream is for, e.g. ``("TEM1", "predict")``.
    """
    return np.random.default_rng([int(seed), *(label_key(k) for k in labels)])


def spawned(seed: int, label: str | int) -> np.random.SeedSequence:
    """The ``SeedSequence`` spawned from the run seed for one label (a module, a stage)."""
    return np.random.SeedSequence(entropy=int(seed), spawn_key=(label_key(label),))


def emcee_seed(rng: np.random.Generator) -> int:
    """A 32-bit seed for emcee's legacy ``RandomState`` drawn from a Generator."""
    return int(rng.integers(0, 2**32 - 1))
