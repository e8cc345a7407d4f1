"""The chi-square consistency test of the glass points against residuals drawn from its own noise model
(known sigma, known outliers, known depth curvature)."""

import numpy as np

from cell.glass.consistency import check_consistency, residual_dof


def test_noise_estimate_outliers_and_depth_sigma():
    rng = np.random.default_rng(11)
    n, sigma = 20000, 40e-6
    cams = rng.integers(1, 5, n)  # 1..4 cameras; 1 = unconfirmed
    dof = residual_dof(cams)
    assert list(residual_dof(np.array([1, 2, 3, 4]))) == [0, 1, 3, 5]
    residual = sigma**2 * rng.chisquare(np.maximum(dof, 1)) * (dof > 0)
    outlier = rng.random(n) < 0.03
    residual[outlier] += (20 * sigma) ** 2  # a camera's normal 20 sigma off
    depth_sigma = rng.uniform(0.01, 0.08, n)  # mm along the normal
    cos_i = rng.uniform(0.5, 1.0, n)
    curvature = 2 * sigma**2 / (depth_sigma / cos_i) ** 2  # least squares: var(t) = 2 sigma^2 / S''
    c = check_consistency(residual, curvature, cams, cos_i, alpha=1e-3, max_depth_sigma_mm=0.05)
    assert abs(c.sigma_rad / sigma - 1) < 0.05  # robust despite 3% outliers
    confirmed = cams >= 2
    assert not c.accepted[~confirmed].any()
    assert np.allclose(c.depth_sigma_mm[confirmed], depth_sigma[confirmed], rtol=0.06)
    good = confirmed & ~outlier & (depth_sigma <= 0.045)
    false_reject = 1 - c.accepted[good].mean()
    assert false_reject < 5e-3  # ~alpha, with the sigma estimated from the data
    assert c.accepted[confirmed & outlier].mean() < 0.01
    assert not c.accepted[depth_sigma > 0.055].any()
