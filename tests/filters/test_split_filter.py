"""SplitCIKalmanFilter: filterpy behaviour unchanged, the split carried through predict and
update, split-CI fusion (atomic), other rules, and the split's meaning in a simulation."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter as FilterpyKF

from cifilter import SplitCIKalmanFilter, split_covariance_intersection

F = np.array([[1.0, 1.0], [0.0, 1.0]])
Q = np.array([[0.25, 0.5], [0.5, 1.0]]) * 0.1


def make(cls, H, R):
    kf = cls(dim_x=2, dim_z=1)
    kf.F, kf.Q, kf.H, kf.R = F.copy(), Q.copy(), H.copy(), np.eye(1) * R
    kf.P = np.diag([10.0, 10.0])
    return kf


def test_same_estimates_as_filterpy_and_the_split_adds_up():
    ours, theirs = make(SplitCIKalmanFilter, np.array([[1.0, 0.0]]), 2.0), \
        make(FilterpyKF, np.array([[1.0, 0.0]]), 2.0)
    g = np.random.default_rng(0)
    for step in range(20):
        ours.predict()
        theirs.predict()
        z = g.standard_normal((1, 1))
        ours.update(z if step % 5 else None)
        theirs.update(z if step % 5 else None)
        np.testing.assert_allclose(ours.x, theirs.x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ours.P, theirs.P, rtol=1e-12)
        np.testing.assert_allclose(ours.P, ours.P_ind + ours.P_dep, rtol=1e-14)
        np.testing.assert_allclose(ours.P_post, ours.P)
    # batch_filter (filterpy's own loop over predict/update) works as well
    zs = [np.array([[v]]) for v in np.linspace(0, 1, 5)]
    means, covariances, _, _ = ours.batch_filter(zs)
    assert means.shape == (5, 2, 1) and np.allclose(covariances[-1], ours.P)


def test_process_noise_goes_to_the_independent_part_and_measurement_noise_too():
    kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.Q, kf.H, kf.R = F, Q, np.array([[1.0, 0.0]]), np.eye(1) * 3.0
    kf.set_split(np.zeros((2, 2)), np.diag([4.0, 1.0]))
    kf.predict()
    np.testing.assert_allclose(kf.P_ind, Q, rtol=1e-14)
    np.testing.assert_allclose(kf.P_dep, F @ np.diag([4.0, 1.0]) @ F.T, rtol=1e-14)
    P_ind, P_dep = kf.P_ind.copy(), kf.P_dep.copy()
    kf.update(np.array([[1.0]]))
    I_KH = np.eye(2) - kf.K @ kf.H
    np.testing.assert_allclose(kf.P_ind, I_KH @ P_ind @ I_KH.T + kf.K @ kf.R @ kf.K.T,
                               rtol=1e-13)
    np.testing.assert_allclose(kf.P_dep, I_KH @ P_dep @ I_KH.T, rtol=1e-13)
    kf.predict(Q=0.5)  # a scalar Q, as filterpy allows
    np.testing.assert_allclose(kf.P, kf.P_ind + kf.P_dep, rtol=1e-14)


def test_fuse_with_another_split_filter_is_split_ci_of_the_parts():
    a = make(SplitCIKalmanFilter, np.array([[1.0, 0.0]]), 1.0)
    b = make(SplitCIKalmanFilter, np.array([[0.0, 1.0]]), 2.0)
    for kf in (a, b):
        kf.predict()
        kf.update(np.array([[0.3]]))
    expected = split_covariance_intersection([a.x, b.x], [a.P_ind, b.P_ind],
                                             [a.P_dep, b.P_dep])
    b_state = (b.x.copy(), b.P.copy(), b.P_ind.copy(), b.P_dep.copy())
    result = a.fuse(b)
    np.testing.assert_allclose(a.P, expected.P, rtol=1e-12)
    np.testing.assert_allclose(a.P_ind, expected.info["P_independent"], rtol=1e-12)
    np.testing.assert_allclose(a.P_dep, expected.info["P_dependent"], rtol=1e-12)
    assert a.x.shape == (2, 1) and a.last_fusion is result
    for before, after in zip(b_state, (b.x, b.P, b.P_ind, b.P_dep)):
        np.testing.assert_array_equal(before, after)  # other is never modified


def test_fuse_with_triples_pairs_partial_estimates_and_other_rules():
    kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
    kf.set_split(np.diag([1.0, 4.0]), np.zeros((2, 2)))
    kf.fuse((np.ones(2), np.diag([4.0, 1.0]), np.zeros((2, 2))))
    np.testing.assert_allclose(kf.P, np.diag([0.8, 0.8]), rtol=1e-12)  # Kalman
    # a plain (x, P) pair is wholly dependent
    kf.set_split(np.zeros((2, 2)), np.diag([1.0, 4.0]))
    r = kf.fuse((np.ones(2), np.diag([4.0, 1.0])))
    assert r.weights[0] == pytest.approx(0.5, abs=1e-9)  # CI, det criterion
    # a partial estimate: a position fix
    kf.set_split(np.eye(2), np.eye(2))
    kf.fuse((np.array([0.5]), 0.1 * np.eye(1), 0.1 * np.eye(1)), H=np.array([[1.0, 0.0]]))
    # the position is fixed; the unobserved velocity keeps its own part and an inflated
    # dependent part (P_dep / omega): split CI pays for the unknown correlation there
    assert kf.P[0, 0] < 0.5 and kf.P[1, 1] > 2.0
    # another rule: the fused P is wholly dependent afterwards
    r = kf.fuse((np.ones(2), np.eye(2)), method="ci")
    assert r.info["criterion"] == "trace"  # CI's own default
    np.testing.assert_array_equal(kf.P_ind, np.zeros((2, 2)))
    r = kf.fuse((np.ones(2), np.eye(2)), method="ci", criterion="det")
    assert r.info["criterion"] == "det"
    np.testing.assert_array_equal(kf.P_dep, kf.P)


def test_fuse_is_atomic_and_direct_assignment_is_dependent():
    kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
    kf.set_split(np.eye(2), 2 * np.eye(2))
    state = (kf.x.copy(), kf.P.copy(), kf.P_ind.copy(), kf.P_dep.copy())
    for bad in ((np.ones(3), np.eye(3), np.eye(3)), (np.ones(2), np.eye(2), -np.eye(2)),
                "filter"):
        with pytest.raises((ValueError, TypeError)):
            kf.fuse(bad)
        for before, after in zip(state, (kf.x, kf.P, kf.P_ind, kf.P_dep)):
            np.testing.assert_array_equal(before, after)
    with pytest.raises(TypeError, match="option"):
        kf.fuse((np.ones(2), np.eye(2), np.eye(2)), rho=0.5)
    kf.P = 5 * np.eye(2)  # filterpy-style assignment
    kf.predict()
    np.testing.assert_allclose(kf.P_ind, kf.Q)
    np.testing.assert_allclose(kf.P_dep, 5 * np.eye(2))
    with pytest.raises(ValueError, match="P_dep"):
        kf.set_split(np.eye(2), -np.eye(2))


def test_split_is_honest_for_a_common_prior():
    """Two filters of a static target start from the same prior error (dependent) and
    measure with their own noise (independent). Their errors are linear in the noises,
    so the true covariance of the fused error is computed exactly (as a linear map of the
    prior error and the six measurement noises) and must lie below the fused P."""
    sigma = np.diag([4.0, 4.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0])  # prior, then noises
    filters, maps = [], []
    for index, (H, R) in enumerate(((np.array([[1.0, 0.0]]), 1.0),
                                    (np.array([[0.0, 1.0]]), 2.0))):
        kf = SplitCIKalmanFilter(dim_x=2, dim_z=1)
        kf.F, kf.Q, kf.H, kf.R = np.eye(2), np.zeros((2, 2)), H, np.eye(1) * R
        kf.P = np.diag([4.0, 4.0])
        error = np.zeros((2, 8))
        error[:, :2] = np.eye(2)  # the common prior error
        for step in range(3):
            kf.predict()
            kf.update(np.array([[0.0]]))
            noise = np.zeros((1, 8))
            noise[0, 2 + 3 * index + step] = 1.0
            error = (np.eye(2) - kf.K @ H) @ error + kf.K @ noise
        filters.append(kf)
        maps.append(error)
    a, b = filters
    # each filter's own P is its exact error covariance
    for kf, error in zip(filters, maps):
        np.testing.assert_allclose(kf.P, error @ sigma @ error.T, rtol=1e-12)
    result = a.fuse(b)
    fused = result.gains[0] @ maps[0] + result.gains[1] @ maps[1]
    true = fused @ sigma @ fused.T
    assert np.linalg.eigvalsh(a.P - true)[0] >= -1e-12
    # the independent part is the exact covariance of the fused measurement-noise error
    noise_part = fused[:, 2:] @ sigma[2:, 2:] @ fused[:, 2:].T
    np.testing.assert_allclose(a.P_ind, noise_part, rtol=1e-10)
