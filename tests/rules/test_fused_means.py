"""Hand-derived fused *means* of two estimates with different covariances.

Every case uses ``P_a = diag(1, 4)``, ``P_b = diag(2, 1)``, ``x_a = (6, 0)``,
``x_b = (0, 6)`` (information ``u = (1, 1/4)`` and ``v = (1/2, 1)``), so that each rule's
mean is a fraction written out by hand below; a rotated copy of the same problem checks the
non-diagonal path (a mean is equivariant: ``x -> Q x``, ``P -> Q P Q^T``), and a batch of
both checks the batched path against the single one.

Information-form rules: ``P^-1 = w_a P_a^-1 + w_b P_b^-1``,
``x = P (w_a P_a^-1 x_a + w_b P_b^-1 x_b)``, so per axis ``k``
``x_k = (w_a u_k x_ak + w_b v_k x_bk) / (w_a u_k + w_b v_k)``.
"""

import math

import numpy as np
import pytest

from cifilter import (
    KalmanFilter,
    covariance_intersection,
    fuse,
    naive_fusion,
    optimal_fusion,
    partial_ci,
    use_backend,
)

PA, PB = np.diag([1.0, 4.0]), np.diag([2.0, 1.0])
XA, XB = np.array([6.0, 0.0]), np.array([0.0, 6.0])
ANGLE = 0.7
Q = np.array([[math.cos(ANGLE), -math.sin(ANGLE)], [math.sin(ANGLE), math.cos(ANGLE)]])
BACKENDS = ["numpy", "numba"]


def rotated(P, x):
    return Q @ P @ Q.T, Q @ x


def check(result, x, P, rtol=1e-12):
    np.testing.assert_allclose(np.ravel(result.x), x, rtol=rtol, atol=rtol * 10)
    np.testing.assert_allclose(result.P, P, rtol=rtol, atol=rtol * 10)


def both_ways(rule, x, P, rtol=1e-12, **options):
    """The hand value on the diagonal problem, its rotation and a batch of the two."""
    check(rule([XA, XB], [PA, PB], **options), x, P, rtol)
    (Pa, xa), (Pb, xb) = rotated(PA, XA), rotated(PB, XB)
    check(rule([xa, xb], [Pa, Pb], **options), Q @ x, Q @ P @ Q.T, rtol)
    batch = rule(np.stack([np.stack([XA, XB]), np.stack([xa, xb])]),
                 np.stack([np.stack([PA, PB]), np.stack([Pa, Pb])]), **options)
    np.testing.assert_allclose(batch.x[0], x, rtol=rtol, atol=rtol * 10)
    np.testing.assert_allclose(batch.x[1], Q @ x, rtol=rtol, atol=rtol * 10)
    np.testing.assert_allclose(batch.P[1], Q @ P @ Q.T, rtol=rtol, atol=rtol * 10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_ci_mean_at_a_given_omega(backend):
    # omega = 1/4: P^-1 = diag(1/4 + 3/8, 1/16 + 3/4) = diag(5/8, 13/16)
    # x = P (1/4 u*x_a + 3/4 v*x_b) = diag(8/5, 16/13) (3/2, 9/2) = (12/5, 72/13)
    with use_backend(backend):
        both_ways(covariance_intersection, np.array([12 / 5, 72 / 13]),
                  np.diag([8 / 5, 16 / 13]), omega=0.25)


@pytest.mark.parametrize("backend", BACKENDS)
def test_ci_mean_at_the_det_optimal_omega(backend):
    # log det P = -sum_k log(w u_k + (1 - w) v_k); stationary where
    # (u_1 - v_1) / D_1 = (v_2 - u_2) / D_2 with D_1 = (1 + w) / 2, D_2 = 1 - 3 w / 4:
    # 1 / (1 + w) = 3 / (4 - 3 w), so w = 1/6. P = diag(12/7, 8/7),
    # x = P ((1/6) u*x_a + (5/6) v*x_b) = diag(12/7, 8/7) (1, 5) = (12/7, 40/7).
    with use_backend(backend):
        r = covariance_intersection([XA, XB], [PA, PB], "det")
        assert r.info["converged"]
        np.testing.assert_allclose(r.omega, [1 / 6, 5 / 6], rtol=1e-10)
        both_ways(covariance_intersection, np.array([12 / 7, 40 / 7]), np.diag([12 / 7, 8 / 7]),
                  rtol=1e-10, criterion="det")


def trace_optimal():
    # trace P = sum_k 1 / D_k; stationary where (1/2) / D_1^2 = (3/4) / D_2^2, so
    # D_2 = s D_1 with s = sqrt(3/2): 1 - 3 w / 4 = s (1 + w) / 2, w = (2 - s) / (3/2 + s).
    s = math.sqrt(1.5)
    w = (2.0 - s) / (1.5 + s)
    D = np.array([w + (1 - w) / 2, w / 4 + (1 - w)])
    x = np.array([w * 6.0, (1 - w) * 6.0]) / D
    return w, x, np.diag(1.0 / D)


@pytest.mark.parametrize("backend", BACKENDS)
def test_ci_mean_at_the_trace_optimal_omega(backend):
    w, x, P = trace_optimal()
    with use_backend(backend):
        r = covariance_intersection([XA, XB], [PA, PB])
        assert r.info["converged"]
        np.testing.assert_allclose(r.omega[0], w, rtol=1e-10)
        both_ways(covariance_intersection, x, P, rtol=1e-10)


def test_naive_mean():
    # P^-1 = diag(1 + 1/2, 1/4 + 1) = diag(3/2, 5/4); x = P (6, 6) = (4, 24/5)
    both_ways(naive_fusion, np.array([4.0, 24 / 5]), np.diag([2 / 3, 4 / 5]))


def test_partial_ci_mean_at_a_given_delta():
    # rho = 1/2, delta = (1/4, 3/4): w_i = delta_i / (rho + (1 - rho) delta_i) = (2/5, 6/7)
    # P^-1 = diag(2/5 + 3/7, 1/10 + 6/7) = diag(29/35, 67/70)
    # x = P ((2/5) u*x_a + (6/7) v*x_b) = P (12/5, 36/7) = (84/29, 360/67)
    both_ways(partial_ci, np.array([84 / 29, 360 / 67]), np.diag([35 / 29, 70 / 67]),
              rho=0.5, delta=[0.25, 0.75])


def test_partial_ci_at_its_ends_is_ci_and_naive():
    # rho = 1: w = delta (CI, the trace optimum above); rho = 0: w = 1 (naive)
    _, x, P = trace_optimal()
    r = partial_ci([XA, XB], [PA, PB], 1.0)
    assert r.info["converged"]
    both_ways(partial_ci, x, P, rtol=1e-9, rho=1.0)
    both_ways(partial_ci, np.array([4.0, 24 / 5]), np.diag([2 / 3, 4 / 5]), rho=0.0)


def blue_scalar(pa, pb, c, xa, xb):
    """Two correlated scalars: W_a = (p_b - c) / (p_a + p_b - 2c), P = (p_a p_b - c^2) / (...)."""
    d = pa + pb - 2 * c
    wa = (pb - c) / d
    return wa * xa + (1 - wa) * xb, (pa * pb - c * c) / d


def test_optimal_mean_with_a_known_cross_covariance():
    # Axes independent: cross covariance diag(1, 1/2). Axis 1: p = (1, 2), c = 1, so
    # W_a = 1, x = 6, P = 1 (x_b adds nothing). Axis 2: p = (4, 1), c = 1/2, d = 4,
    # W_a = 1/8, x = 7/8 * 6 = 21/4, P = 15/16.
    C = np.diag([1.0, 0.5])
    joint = np.block([[PA, C], [C.T, PB]])
    expected = [blue_scalar(1.0, 2.0, 1.0, 6.0, 0.0), blue_scalar(4.0, 1.0, 0.5, 0.0, 6.0)]
    assert expected == [(6.0, 1.0), (21 / 4, 15 / 16)]
    r = optimal_fusion([XA, XB], joint)
    np.testing.assert_allclose(r.x, [6.0, 21 / 4], rtol=1e-12)
    np.testing.assert_allclose(r.P, np.diag([1.0, 15 / 16]), rtol=1e-12, atol=1e-14)
    # rotated: the same problem in another basis
    R2 = np.kron(np.eye(2), Q)
    rr = optimal_fusion([Q @ XA, Q @ XB], R2 @ joint @ R2.T)
    np.testing.assert_allclose(rr.x, Q @ np.array([6.0, 21 / 4]), rtol=1e-12)


def test_optimal_mean_with_a_non_symmetric_cross_covariance():
    # Minimise tr(K J K^T) subject to K_a + K_b = I by its KKT system, solved here directly
    # (an independent reference): [[2 J, E], [E^T, 0]] [K^T; Lambda] = [0; I].
    C = np.array([[0.3, 0.8], [-0.2, 0.1]])
    joint = np.block([[PA, C], [C.T, PB]])
    assert np.linalg.eigvalsh(joint).min() > 0
    E = np.vstack([np.eye(2), np.eye(2)])
    kkt = np.block([[2 * joint, E], [E.T, np.zeros((2, 2))]])
    KT = np.linalg.solve(kkt, np.vstack([np.zeros((4, 2)), np.eye(2)]))[:4]
    K = KT.T
    x = K @ np.concatenate([XA, XB])
    P = K @ joint @ K.T
    r = optimal_fusion([XA, XB], joint)
    np.testing.assert_allclose(r.x, x, rtol=1e-12)
    np.testing.assert_allclose(r.P, P, rtol=1e-12)
    np.testing.assert_allclose(r.gains[0], K[:, :2], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("method, options, x, P", [
    ("ci", {"omega": 0.25}, [12 / 5, 72 / 13], np.diag([8 / 5, 16 / 13])),
    ("naive", {}, [4.0, 24 / 5], np.diag([2 / 3, 4 / 5])),
    ("pci", {"rho": 0.5, "delta": [0.25, 0.75]}, [84 / 29, 360 / 67],
     np.diag([35 / 29, 70 / 67])),
])
def test_filter_fuse_mean(method, options, x, P):
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P = XA.reshape(2, 1).copy(), PA.copy()
    kf.fuse((XB, PB.copy()), method, **options)
    np.testing.assert_allclose(kf.x.ravel(), x, rtol=1e-12)
    np.testing.assert_allclose(kf.P, P, rtol=1e-12, atol=1e-14)
    assert kf.x.shape == (2, 1)
    # and the front door gives the same
    r = fuse([(XA, PA), (XB, PB)], method=method, **options)
    np.testing.assert_allclose(np.ravel(r.x), x, rtol=1e-12)
