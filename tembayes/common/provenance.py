"""Versions of tembayes and the packages that shape its numbers, for outputs' provenance."""

from __future__ import annotations

import sys
from importlib.metadata import PackageNotFoundError, version

import tembayes

PACKAGES = ("numpy", "scipy", "numba", "emcee", "arviz", "corner", "matplotlib")


def versions() -> dict[str, str | None]:
    """``{"tembayes", "python", package: version}`` (``None`` for a package not installed)."""
    out = {"tembayes": tembayes.__version__, "python": sys.version.split()[0]}
    for p in PACKAGES:
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            out[p] = None
    return out
