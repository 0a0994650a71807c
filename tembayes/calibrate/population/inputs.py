"""Checks of what the population fits are given: modules, their draws, the random generator."""

from __future__ import annotations

import numpy as np

from tembayes.calibrate.population.model import LEVEL, N_PARAMS
from tembayes.common.seeds import emcee_seed
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import ModelError

#: A module needs at least this many posterior draws.
MIN_DRAWS = 20
#: A population needs at least this many modules.
MIN_MODULES = 2


def check_modules(mapping, what):
    """The module ids of a ``dict`` module id -> ... with at least :data:`MIN_MODULES` entries."""
    if not isinstance(mapping, dict):
        raise ModelError(f"{what} must be a dict module id -> ..., got {type(mapping).__name__}")
    if len(mapping) < MIN_MODULES:
        raise ModelError(f"a population needs at least {MIN_MODULES} modules, got {len(mapping)} ({list(mapping)})")
    return tuple(mapping)


def _check_draws(mid, a):
    """One module's draws as a float array (M, 5), or a ModelError naming the module."""
    try:
        a = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise ModelError(f"module '{mid}': draws are not a numeric array") from None
    if a.ndim != 2 or a.shape[1] != N_PARAMS:
        raise ModelError(
            f"module '{mid}': draws must have shape (n_draws, {N_PARAMS}) in the order "
            f"{MODULE_PARAMETERS}, got shape {a.shape}"
        )
    if len(a) < MIN_DRAWS:
        raise ModelError(f"module '{mid}': needs at least {MIN_DRAWS} posterior draws, got {len(a)}")
    bad = ~np.isfinite(a)
    if bad.any():
        cols = [MODULE_PARAMETERS[j] for j in np.flatnonzero(bad.any(axis=0))]
        raise ModelError(f"module '{mid}': {int(bad.sum())} non-finite draw values (NaN/inf) in {cols}")
    nonpos = (a[:, LEVEL] <= 0).any(axis=0)
    if nonpos.any():
        cols = [p for p, lev in zip(MODULE_PARAMETERS, LEVEL) if lev]
        cols = [c for c, b in zip(cols, nonpos) if b]
        raise ModelError(f"module '{mid}': {cols} must be positive in every draw")
    flat = np.ptp(a, axis=0) == 0
    if flat.any():
        raise ModelError(
            f"module '{mid}': draws of {[MODULE_PARAMETERS[j] for j in np.flatnonzero(flat)]} "
            "do not vary (a posterior needs spread)"
        )
    return a


def validate_draws(draws):
    """Module ids and their checked draws (list of float arrays (M_i, 5)).

    Raises
    ------
    ModelError
        Not a dict, fewer than :data:`MIN_MODULES` modules, or a module's
        draws malformed, too few, non-finite, non-positive levels, or constant.
    """
    ids = check_modules(draws, "draws")
    return ids, [_check_draws(mid, draws[mid]) for mid in ids]


def sampler_seed(rng):
    """The seed of emcee's random state, drawn from the caller's generator.

    Raises
    ------
    ModelError
        ``rng`` is not a ``numpy.random.Generator``.
    """
    if not isinstance(rng, np.random.Generator):
        raise ModelError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    return emcee_seed(rng)
