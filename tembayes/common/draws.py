"""Even thinning of draws."""

from __future__ import annotations

import numpy as np


def even_indices(n: int, k: int) -> np.ndarray:
    """At most ``k`` indices into ``n`` items, evenly spread and including both ends.

    The indices are unique and increasing (for ``k <= n`` their spacing is at
    least one).
    """
    return np.linspace(0, n - 1, min(int(n), int(k))).round().astype(int)


def thin(x: np.ndarray, k: int) -> np.ndarray:
    """The rows of ``x`` at :func:`even_indices` (all rows when there are at most ``k``)."""
    return x if len(x) <= k else x[even_indices(len(x), k)]
