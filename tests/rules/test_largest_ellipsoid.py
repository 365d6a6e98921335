"""Largest-ellipsoid (safe) fusion (:mod:`cifilter.rules.largest_ellipsoid`, ``"le"``).

Its covariance is EI's and its mean EI's with ``eps=0`` (proved on the method's page, checked
here at condition numbers up to 1e12); the relation to CI in one dimension and for
``Pa <= Pb``; ``P`` lies inside both inputs and inside CI's bound; no guarantee (a joint for
which the error covariance of its gains exceeds ``P``); conventions and bad input.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_sets, means_of_their_scale, spd_matrices
from worst_case import assert_unbiased, worst_case_variance

from cifilter import (
    KalmanFilter,
    covariance_intersection,
    ellipsoidal_intersection,
    fuse,
    get_method,
    largest_ellipsoid,
)

EPS = np.finfo(float).eps


def assert_psd(M, tol, what):
    smallest = np.linalg.eigvalsh(0.5 * (M + M.T)).min()
    assert smallest >= -tol, f"{what}: smallest eigenvalue {smallest:.3g}"


def test_each_input_keeps_its_better_axis():
    r = largest_ellipsoid([np.array([1.0, 0.0]), np.array([0.0, 1.0])],
                          [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])])
    np.testing.assert_allclose(r.x, [1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(r.P, np.eye(2), atol=1e-12)
    assert r.method == "le" and r.weights is None and int(r.info["ties"]) == 0


def test_safe_fusion_algorithm_written_out():
    """Algorithm 1 of Nygårds, Deleskog & Hendeby (2016) step by step, with inverses."""
    g = np.random.default_rng(4)
    A, B = g.standard_normal((2, 3, 3))
    Pa, Pb = A @ A.T + 0.1 * np.eye(3), B @ B.T + 0.1 * np.eye(3)
    xa, xb = g.standard_normal((2, 3))
    D1, U1 = np.linalg.eigh(Pa)
    T1 = np.diag(D1 ** -0.5) @ U1.T
    D2, U2 = np.linalg.eigh(T1 @ Pb @ T1.T)
    T = U2.T @ T1
    ya, yb = T @ xa, T @ xb
    y = np.where(D2 >= 1.0, ya, yb)  # I in a's, D2 in b's variances: keep the smaller
    x = np.linalg.solve(T, y)
    P = np.linalg.inv(T) @ np.diag(np.minimum(1.0, D2)) @ np.linalg.inv(T).T
    r = largest_ellipsoid([xa, xb], [Pa, Pb])
    np.testing.assert_allclose(r.x, x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.P, P, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("pa, pb", [(1.0, 4.0), (9.0, 0.5), (2.0, 2.0 + 1e-9)])
def test_one_dimension_equals_ci(pa, pb):
    xs, Ps = [np.array([1.0]), np.array([-2.0])], [np.array([[pa]]), np.array([[pb]])]
    le, ci = largest_ellipsoid(xs, Ps), covariance_intersection(xs, Ps)
    np.testing.assert_allclose(le.P, ci.P, rtol=1e-12)
    np.testing.assert_allclose(le.x, ci.x, rtol=1e-12)
    assert le.P[0, 0] == pytest.approx(min(pa, pb), rel=1e-14)


def test_equal_variances_average_the_means():
    r = largest_ellipsoid([np.array([1.0]), np.array([3.0])], [np.eye(1), np.eye(1)])
    assert r.x.tolist() == [2.0] and r.P.tolist() == [[1.0]] and int(r.info["ties"]) == 1


@settings(max_examples=30)
@given(st.integers(1, 4), st.data())
def test_dominated_input_returns_the_better_one(n, data):
    Pa = data.draw(spd_matrices(n))
    Pb = Pa + data.draw(spd_matrices(n))  # Pa <= Pb
    xa, xb = np.arange(n) * 0.5, -np.ones(n)
    r = largest_ellipsoid([xa, xb], [Pa, Pb])
    np.testing.assert_allclose(r.x, xa, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r.P, Pa, rtol=1e-9, atol=1e-9 * np.abs(Pa).max())
    ci = covariance_intersection([xa, xb], [Pa, Pb])  # optimal CI does the same
    np.testing.assert_allclose(ci.P, Pa, rtol=1e-7, atol=1e-9 * np.abs(Pa).max())


@settings(max_examples=40)
@given(st.integers(1, 4), ill_conditioned_sets(2, 4),
       st.lists(st.floats(-3, 3), min_size=10, max_size=10))
def test_equals_ei_covariance_and_eps0_mean_ill_conditioned(n, Ps, values):
    Pa, Pb = Ps[0][:n, :n], Ps[1][:n, :n]
    xa, xb = means_of_their_scale(values, Pa, Pb)
    le = largest_ellipsoid([xa, xb], [Pa, Pb])
    ei = ellipsoidal_intersection([xa, xb], [Pa, Pb])  # default eps: the same P
    ei0 = ellipsoidal_intersection([xa, xb], [Pa, Pb], eps=0.0)
    np.testing.assert_array_equal(le.P, ei.P)
    np.testing.assert_array_equal(le.P, ei0.P)
    scale = np.sqrt(np.diag(le.P))  # means compared in standard deviations of P
    np.testing.assert_allclose(le.x / scale, ei0.x / scale, atol=1e-9)
    assert np.array_equal(le.P, le.P.T) and np.isfinite(le.P).all()
    np.linalg.cholesky(le.P)
    assert_unbiased(le.gains)
    np.testing.assert_allclose(le.gains[0] @ xa + le.gains[1] @ xb, le.x,
                               atol=1e-9 * (np.abs(xa).max() + np.abs(xb).max() + 1e-300))


@settings(max_examples=30)
@given(st.integers(1, 4), st.data())
def test_inside_both_inputs_and_inside_ci(n, data):
    Pa, Pb = data.draw(spd_matrices(n)), data.draw(spd_matrices(n))
    le = largest_ellipsoid([np.zeros(n)] * 2, [Pa, Pb])
    ci = covariance_intersection([np.zeros(n)] * 2, [Pa, Pb])
    tol = 1e-10 * max(np.abs(Pa).max(), np.abs(Pb).max())
    assert_psd(Pa - le.P, tol, "Pa - P_LE")
    assert_psd(Pb - le.P, tol, "Pb - P_LE")
    assert_psd(ci.P - le.P, tol, "P_CI - P_LE")  # CI's ellipsoid contains the intersection


def test_no_guarantee_a_joint_it_does_not_bound():
    """Keeping a's first and b's second axis: a correlation between those two components
    gives the fused error an off-diagonal covariance that P = I does not bound."""
    Ps = [np.diag([1.0, 4.0]), np.diag([4.0, 1.0])]
    r = largest_ellipsoid([np.zeros(2)] * 2, Ps)
    v = np.array([1.0, 1.0]) / np.sqrt(2.0)
    worst = float(worst_case_variance(r.gains, Ps, v))  # the exact worst case along v
    assert worst == pytest.approx(2.0) and v @ r.P @ v == pytest.approx(1.0)


def test_batch_permutation_registry_filter_and_no_mutation():
    g = np.random.default_rng(2)
    A = g.standard_normal((5, 2, 3, 3))
    Ps = A @ A.swapaxes(-1, -2) + 0.1 * np.eye(3)
    xs = g.standard_normal((5, 2, 3))
    copies = xs.copy(), Ps.copy()
    batch = largest_ellipsoid(xs, Ps)
    swapped = largest_ellipsoid(xs[:, ::-1], Ps[:, ::-1])
    assert np.array_equal(xs, copies[0]) and np.array_equal(Ps, copies[1])
    for k in range(5):
        one = largest_ellipsoid(list(xs[k]), list(Ps[k]))
        np.testing.assert_allclose(batch.x[k], one.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(batch.P[k], one.P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(swapped.x, batch.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(swapped.P, batch.P, rtol=1e-9, atol=1e-12)
    via = fuse([(xs[0, 0], Ps[0, 0]), (xs[0, 1], Ps[0, 1])], method="le")
    np.testing.assert_array_equal(via.P, largest_ellipsoid(list(xs[0]), list(Ps[0])).P)
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.x, kf.P = xs[0, 0][:, None].copy(), Ps[0, 0].copy()
    kf.fuse((xs[0, 1], Ps[0, 1]), method="le")
    assert kf.x.shape == (3, 1)
    np.testing.assert_allclose(kf.P, via.P)
    assert get_method("le").guarantee == "none"


def test_bad_input():
    with pytest.raises(ValueError, match="exactly two"):
        largest_ellipsoid([np.zeros(2)] * 3, [np.eye(2)] * 3)
    with pytest.raises(ValueError, match="positive definite"):
        largest_ellipsoid([np.zeros(2)] * 2, [np.eye(2), np.diag([1.0, -1.0])])
    with pytest.raises(TypeError):
        largest_ellipsoid([np.zeros(2)] * 2, ["a", "b"])
