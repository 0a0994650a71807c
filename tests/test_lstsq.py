"""The least-squares covariance on coordinates of very different scales."""

import numpy as np

from tembayes.common.lstsq import design_covariance


def _badly_scaled_design():
    """A design whose columns span 12 decades, with a tight but known ridge between two of them."""
    rng = np.random.default_rng(3)
    A0 = rng.standard_normal((400, 4))
    A0[:, 3] = A0[:, 2] + 0.01 * rng.standard_normal(400)  # a ridge: correlation ~0.99995
    D = np.diag([1e-8, 1.0, 1e2, 1e4])  # coordinate scales
    truth = D @ np.linalg.inv(A0.T @ A0) @ D
    return A0 @ np.linalg.inv(D), truth


def test_the_covariance_of_a_badly_scaled_design_keeps_its_weakest_direction():
    A, truth = _badly_scaled_design()
    cov = design_covariance(A)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(truth)), rtol=1e-6)
    np.testing.assert_allclose(
        cov[2, 3] / np.sqrt(cov[2, 2] * cov[3, 3]), truth[2, 3] / np.sqrt(truth[2, 2] * truth[3, 3]), rtol=1e-6
    )
    # the plain pseudo-inverse loses the ridge: the failure this guards against
    naive = np.linalg.pinv(A.T @ A)
    assert np.sqrt(naive[3, 3]) < 0.1 * np.sqrt(truth[3, 3])


def test_a_coordinate_the_data_do_not_see_gets_zero_covariance():
    A, _ = _badly_scaled_design()
    A[:, 1] = 0.0
    cov = design_covariance(A)
    assert np.all(cov[1] == 0.0) and np.all(cov[:, 1] == 0.0)
    assert np.all(np.isfinite(cov)) and np.all(np.diag(cov)[[0, 2, 3]] > 0)
