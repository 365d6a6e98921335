"""PC-EI on ill-conditioned inputs: the conditioning contract (issue 9, item 3).

PC-EI starts from EI's common covariance and returns EI where the constraint holds, so
it inherited EI's indefinite covariances; the rest of its tests are in test_ei.py.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import ill_conditioned_sets, means_of_their_scale
from test_ei import (
    METRIC_TOL,
    assert_valid_fusion,
    issue_pair,
    metric_difference,
    within_contract,
)

from cifilter import ellipsoidal_intersection, pc_ellipsoidal_intersection
from cifilter._linalg import IllConditionedError

ill_pairs = st.integers(1, 5).flatmap(lambda n: st.booleans().flatmap(
    lambda common: ill_conditioned_sets(2, n, common_scale=common)))
unit = st.floats(-2.0, 2.0, allow_nan=False)


def pc_or_contract_error(xa, Pa, xb, Pb, **options):
    try:
        return pc_ellipsoidal_intersection(xa, Pa, xb, Pb, **options)
    except IllConditionedError:
        assert not within_contract(Pa, Pb)
        return None


def assert_honest_flags(r):
    info = r.info
    if info["active"] and info["feasible"] and info["converged"]:
        assert info["psi"] <= info["threshold"] * (1 + 1e-6)


@settings(max_examples=60)
@given(ill_pairs, st.lists(unit, min_size=10, max_size=10),
       st.sampled_from(["as-printed", "sijs-lazar"]),
       st.sampled_from([("information", 1e-8), ("covariance", 0.01)]))
def test_pc_is_positive_definite_on_ill_conditioned_pairs(Ps, values, mutual_mean,
                                                          regularization):
    Pa, Pb = Ps
    xa, xb = means_of_their_scale(values, Pa, Pb)
    regularizer, eps = regularization
    r = pc_or_contract_error(xa, Pa, xb, Pb, mutual_mean=mutual_mean,
                             regularizer=regularizer, eps=eps)
    if r is None:
        return
    assert_valid_fusion(r, Pa, Pb)
    assert_honest_flags(r)
    np.testing.assert_allclose(r.gains[0] @ xa + r.gains[1] @ xb, r.x, rtol=1e-9,
                               atol=1e-9 * (np.abs(xa).max() + np.abs(xb).max()))
    if regularizer == "information":
        # a larger common covariance than EI's: P <= P_EI <= Pa, Pb (in P's metric)
        L = np.linalg.cholesky(r.P)
        for Q in (Pa, Pb):
            X = np.linalg.solve(L, np.linalg.solve(L, Q).T)
            assert np.linalg.eigvalsh(0.5 * (X + X.T))[0] >= 1 - METRIC_TOL


@settings(max_examples=40)
@given(ill_pairs, st.lists(unit, min_size=5, max_size=5))
def test_pc_with_equal_covariances_is_positive_definite_and_symmetric(Ps, values):
    """Ties everywhere (the closed form): the common part grows along the mean difference."""
    Pa = Ps[0]
    n = Pa.shape[0]
    e = np.array(values[:n]) * np.sqrt(np.diag(Pa))
    r = pc_or_contract_error(e, Pa, -e, Pa.copy())
    if r is None:
        return
    assert_valid_fusion(r, Pa, Pa)
    swapped = pc_ellipsoidal_intersection(-e, Pa, e, Pa.copy())
    assert metric_difference(r.P, swapped.P) <= 1e-8


@settings(max_examples=25)
@given(st.integers(1, 4).flatmap(lambda n: st.lists(ill_conditioned_sets(2, n), min_size=3,
                                                     max_size=3)),
       st.sampled_from(["as-printed", "sijs-lazar"]))
def test_pc_batched_ill_conditioned_pairs_are_positive_definite(pairs_, mutual_mean):
    Pa = np.stack([p[0] for p in pairs_])
    Pb = np.stack([p[1] for p in pairs_])
    n = Pa.shape[-1]
    xa = np.sqrt(np.diagonal(Pa, axis1=-2, axis2=-1))
    xb = -np.sqrt(np.diagonal(Pb, axis1=-2, axis2=-1))
    r = pc_or_contract_error(xa, Pa, xb, Pb, mutual_mean=mutual_mean)
    if r is None:
        return
    assert r.P.shape == (3, n, n)
    assert_valid_fusion(r, Pa, Pb)


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_pc_returns_ei_where_the_constraint_holds_on_ill_conditioned_pairs(mutual_mean):
    """Equal means pass the test: PC-EI is EI exactly, also at condition number 1e11."""
    rng = np.random.default_rng(7)
    Pa = np.stack([issue_pair(rng, 3, 1e11) for _ in range(20)])
    Pb = np.stack([issue_pair(rng, 3, 1e11) for _ in range(20)])
    x = rng.standard_normal((20, 3))
    ei = ellipsoidal_intersection(x, Pa, x, Pb, mutual_mean=mutual_mean)
    pc = pc_ellipsoidal_intersection(x, Pa, x, Pb, mutual_mean=mutual_mean)
    assert np.all(pc.info["solver"] == "ei")
    np.testing.assert_array_equal(pc.P, ei.P)
    assert_valid_fusion(pc, Pa, Pb)
