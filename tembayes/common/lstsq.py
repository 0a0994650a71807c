"""The covariance of a linear least-squares estimate, robust to badly scaled columns."""

from __future__ import annotations

import numpy as np

#: Singular values of the column-scaled design below this fraction of the largest are treated as zero.
RCOND = 1e-12


def design_covariance(A: np.ndarray) -> np.ndarray:
    """``(A^T A)^-1`` of a whitened design ``A`` ``(m, p)``, computed on unit-norm columns.

    The coordinates of a calibration differ in scale by many orders (a
    log conductance against an S1 of 1e-4 V/K^2), so ``A^T A`` spans ~16
    decades and a plain pseudo-inverse drops its weakest directions as if
    they were infinitely well known: on the example's TEM2 the bottom leak's
    tab share came out with an sd of 0.004 instead of 0.34.  Scaling every
    column to unit norm first leaves only the problem's own conditioning.
    A column of zeros (a coordinate the data do not see) gets a zero row and
    column, as the pseudo-inverse gives.

    Parameters
    ----------
    A : ndarray, shape (m, p)

    Returns
    -------
    ndarray, shape (p, p)
    """
    A = np.asarray(A, dtype=float)
    s = np.sqrt(np.sum(A * A, axis=0))
    seen = s > 0
    _, sv, Vt = np.linalg.svd(A[:, seen] / s[seen], full_matrices=False)
    inv = np.where(sv > RCOND * sv[0], 1.0 / np.where(sv > 0, sv, 1.0) ** 2, 0.0)
    cov = np.zeros((A.shape[1], A.shape[1]))
    cov[np.ix_(seen, seen)] = (Vt.T * inv) @ Vt / np.outer(s[seen], s[seen])
    return cov
