"""cifilter.metrics against hand-computed cases and scipy."""

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.distance import mahalanobis

from cifilter import metrics


def test_nees_hand_case_and_styles():
    # e = (2, 1), P = diag(4, 1): 4/4 + 1/1 = 2
    assert metrics.nees(np.zeros(2), np.array([2.0, 1.0]), np.diag([4.0, 1.0])) == 2.0
    column = metrics.nees(np.zeros((2, 1)), np.array([[2.0], [1.0]]), np.diag([4.0, 1.0]))
    assert float(column) == 2.0
    # correlated P: e^T P^-1 e by hand, P = [[2, 1], [1, 2]], P^-1 = [[2, -1], [-1, 2]] / 3
    e = np.array([1.0, 2.0])
    expected = (2 * 1 - 2 * 1 * 2 + 2 * 4) / 3.0
    assert metrics.nees(np.zeros(2), e, [[2.0, 1.0], [1.0, 2.0]]) == pytest.approx(expected)


def test_nees_batched_agrees_with_scipy_mahalanobis():
    rng = np.random.default_rng(3)
    A = rng.standard_normal((5, 7, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    truth, x = rng.standard_normal((5, 7, 3)), rng.standard_normal((5, 7, 3))
    values = metrics.nees(truth, x, P)
    assert values.shape == (5, 7)
    for i, j in [(0, 0), (2, 5), (4, 6)]:
        expected = mahalanobis(x[i, j], truth[i, j], np.linalg.inv(P[i, j])) ** 2
        assert values[i, j] == pytest.approx(expected, rel=1e-12)
    # one covariance broadcast over the batch
    assert metrics.nees(truth, x, P[0, 0]).shape == (5, 7)


def test_nis_is_the_normalised_innovation():
    assert float(metrics.nis(np.array([3.0]), np.array([[9.0]]))) == 1.0
    assert metrics.nis(np.ones((4, 2)), np.eye(2)).tolist() == [2.0] * 4


def test_nees_rejects_bad_input():
    with pytest.raises(ValueError, match="P must have shape"):
        metrics.nees(np.zeros(2), np.ones(2), np.eye(3))
    with pytest.raises(ValueError, match="positive definite"):
        metrics.nees(np.zeros(2), np.ones(2), -np.eye(2))


def test_chi2_bounds_are_the_scipy_quantiles():
    lower, upper = metrics.chi2_bounds(4, 50, confidence=0.95)
    assert lower == pytest.approx(stats.chi2.ppf(0.025, 200) / 50)
    assert upper == pytest.approx(stats.chi2.ppf(0.975, 200) / 50)
    assert lower < 4 < upper
    # one run, one dimension: the chi-square(1) quantiles themselves
    assert metrics.chi2_bounds(1, 1, 0.9) == pytest.approx(stats.chi2.ppf([0.05, 0.95], 1))
    with pytest.raises(ValueError, match="runs"):
        metrics.chi2_bounds(2, 0)
    with pytest.raises(ValueError, match="confidence"):
        metrics.chi2_bounds(2, 10, confidence=1.0)


def test_anees_value_bounds_share_and_verdicts():
    values = np.array([[1.0, 2.0, 30.0], [3.0, 2.0, 30.0]])  # 2 runs, 3 steps, dim 2
    result = metrics.anees(values, dim=2)
    assert result.value.tolist() == [2.0, 2.0, 30.0]
    assert (result.lower, result.upper) == pytest.approx(metrics.chi2_bounds(2, 2))
    assert result.inside.tolist() == [True, True, False]
    assert result.share_inside == pytest.approx(2 / 3)
    assert result.mean == pytest.approx(34 / 3)
    assert result.verdict == "overconfident"
    assert metrics.anees(np.full((100, 4), 0.5), dim=2).verdict == "conservative"
    # the runs on another axis
    assert metrics.anees(values.T, dim=2, axis=1).value.tolist() == [2.0, 2.0, 30.0]
    with pytest.raises(ValueError, match="non-negative"):
        metrics.anees(np.array([-1.0]), dim=1)


def test_anees_of_a_consistent_estimator_is_inside_its_bounds_about_95_percent():
    rng = np.random.default_rng(11)
    errors = rng.standard_normal((40, 500, 3))  # 40 runs, 500 steps, P = I
    result = metrics.anees(metrics.nees(np.zeros(3), errors, np.eye(3)), dim=3)
    assert 0.92 < result.share_inside < 0.98
    assert result.verdict == "consistent"


def test_rmse_hand_case_components_and_axes():
    errors = np.array([[3.0, 4.0], [0.0, 0.0]])  # two runs: squared errors 25 and 0
    assert metrics.rmse(np.zeros(2), errors) == pytest.approx(np.sqrt(12.5))
    assert metrics.rmse(np.zeros(2), errors, components=[1]) == pytest.approx(np.sqrt(8.0))
    per_step = metrics.rmse(np.zeros((2, 3, 2)), np.ones((2, 3, 2)))
    assert per_step.tolist() == pytest.approx([np.sqrt(2.0)] * 3)
    assert metrics.rmse(np.zeros((2, 3, 2)), np.ones((2, 3, 2)), axis=None) == \
        pytest.approx(np.sqrt(2.0))


def test_conservativeness_eigenvalue_hand_case():
    # errors with second moment exactly diag(1, 4); P = 2 I: eigenvalues 2 and 0.5
    s = np.sqrt(2.0)
    errors = np.array([[s, 0.0], [-s, 0.0], [0.0, 2 * s], [0.0, -2 * s]])
    result = metrics.conservativeness(2.0 * np.eye(2), errors)
    assert result.eigenvalue == pytest.approx(0.5)
    assert result.lower < 0.5 < result.upper
    assert result.samples == 4


def test_conservativeness_verdicts_and_batch():
    rng = np.random.default_rng(5)
    errors = rng.standard_normal((2000, 3, 2))  # true covariance I, three problems
    P = np.stack([3.0 * np.eye(2), np.eye(2), 0.3 * np.eye(2)])
    result = metrics.conservativeness(P, errors)
    assert result.eigenvalue.shape == (3,)
    assert result.verdict.tolist() == ["conservative", "inconclusive", "overconfident"]


def test_conservativeness_interval_covers_the_truth():
    """With P equal to the true covariance the interval contains 1 at least ~95% of the
    time (it is a union bound, so usually more)."""
    rng = np.random.default_rng(8)
    Sigma = np.array([[2.0, 0.8], [0.8, 1.0]])
    L = np.linalg.cholesky(Sigma)
    errors = rng.standard_normal((300, 100, 2)) @ L.T  # 300 repetitions of 100 samples
    result = metrics.conservativeness(Sigma, np.swapaxes(errors, 0, 1))
    covered = np.mean((result.lower <= 1.0) & (1.0 <= result.upper))
    assert covered >= 0.93


def test_conservativeness_rejects_too_few_samples():
    with pytest.raises(ValueError, match="at least 3 error samples"):
        metrics.conservativeness(np.eye(3), np.zeros((2, 3)))
