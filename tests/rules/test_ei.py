"""Ellipsoidal Intersection (:mod:`cifilter.rules.ei`), through its public function and fuse.

The literal eqs. (11)-(13) and (17), hand-derived cases, properties, the conditioning
contract, the argument forms, batching, conventions and bad input. Helpers shared with
``test_pcei.py`` live here (``check_*`` functions take the rule under test). The paper's
Section III case 1 (``cifilter.cli.reproduce.naveen``) is in ``test_reproduce.py``.
"""

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given
from hypothesis import strategies as st
from strategies import ill_conditioned_sets, means_of_their_scale, spd_matrices

import cifilter
from cifilter import IllConditionedError, ellipsoidal_intersection, fuse

inv = np.linalg.inv


def random_spd(n, size=(), seed=0, scale=1.0):
    A = np.random.default_rng(seed).standard_normal(size + (n, n))
    return scale * (A @ np.swapaxes(A, -1, -2) / n + 0.2 * np.eye(n))


def setup_problem(n, seed, dominated=False):
    g = np.random.default_rng(seed)
    Pa = random_spd(n, seed=seed)
    Pb = Pa + random_spd(n, seed=seed + 1) if dominated else random_spd(n, seed=seed + 1)
    xa = g.standard_normal(n) * 0.5
    xb = g.standard_normal(n) * 0.5
    return xa, Pa, xb, Pb

# ----------------------------------------------------------------- literal formulas
def literal_ei(xa, Pa, xb, Pb, eps, mutual_mean):
    """Eqs. (11)-(13) and (5)-(8) of Naveen & Taylor written out as printed."""
    d_a, E_a = np.linalg.eigh(Pa)  # C_a = E_a D_a E_a^T        (eq. 12)
    root = np.diag(np.sqrt(d_a))
    d_b, Q_b = np.linalg.eigh(inv(root) @ E_a.T @ Pb @ E_a @ inv(root))
    D_c = np.diag(np.maximum(d_b, 1.0))  # D_Cc = max(D_b, 1)   (eq. 11)
    Cc = E_a @ root @ Q_b @ D_c @ Q_b.T @ root @ E_a.T + eps * np.eye(len(xa))
    Ia, Ib, Ic = inv(Pa) - inv(Cc), inv(Pb) - inv(Cc), inv(Cc)  # eq. (6)
    if mutual_mean == "as-printed":  # eq. (13)
        mc = inv(inv(Pa) + inv(Pb) - 2 * Ic) @ (Ia @ xa + Ib @ xb)
    else:  # Sijs & Lazar (2012), eq. (16) with eta = 0
        mc = inv(Ia + Ib) @ (Ib @ xa + Ia @ xb)
    P = inv(inv(Pa) + inv(Pb) - Ic)  # eq. (8)
    x = P @ (inv(Pa) @ xa + inv(Pb) @ xb - Ic @ mc)  # eq. (7) with eq. (5)
    return x, P, Cc, mc


def literal_psi(xa, Pa, xb, Pb, Cc, mutual_mean):
    """Eq. (17) with eqs. (5), (6) and (13) for an admissible, strictly larger C_c."""
    Ca_c, Cb_c = inv(inv(Pa) - inv(Cc)), inv(inv(Pb) - inv(Cc))
    if mutual_mean == "as-printed":
        mc = inv(inv(Ca_c) + inv(Cb_c)) @ (inv(Ca_c) @ xa + inv(Cb_c) @ xb)
    else:
        mc = inv(inv(Ca_c) + inv(Cb_c)) @ (inv(Cb_c) @ xa + inv(Ca_c) @ xb)
    ma = Ca_c @ (inv(Pa) @ xa - inv(Cc) @ mc)
    mb = Cb_c @ (inv(Pb) @ xb - inv(Cc) @ mc)
    return (ma - mb) @ inv(Ca_c + Cb_c) @ (ma - mb)


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_ei_matches_the_printed_equations(mutual_mean, n):
    Pa, Pb = random_spd(n, seed=n), random_spd(n, seed=10 + n)
    g = np.random.default_rng(n)
    xa, xb = g.standard_normal(n), g.standard_normal(n)
    x, P, Cc, mc = literal_ei(xa, Pa, xb, Pb, 0.01, mutual_mean)
    r = ellipsoidal_intersection(xa, Pa, xb, Pb, eps=0.01, regularizer="covariance",
                                 mutual_mean=mutual_mean)
    np.testing.assert_allclose(r.info["common_P"], Cc, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r.info["common_x"], mc, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(r.P, P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r.x, x, rtol=1e-7, atol=1e-9)
    assert r.info["psi"] == pytest.approx(literal_psi(xa, Pa, xb, Pb, Cc, mutual_mean),
                                          rel=1e-6)


# ----------------------------------------------------------------- EI: hand-derived cases
def test_ei_takes_the_better_input_per_eigen_direction():
    Pa, Pb = np.diag([1.0, 4.0]), np.diag([4.0, 1.0])
    xa, xb = np.array([1.0, 2.0]), np.array([-3.0, 5.0])
    for eps in (0.0, 1e-8):
        r = ellipsoidal_intersection(xa, Pa, xb, Pb, eps=eps)
        np.testing.assert_allclose(r.P, np.eye(2), atol=1e-15)
        np.testing.assert_allclose(r.info["common_P"], 4 * np.eye(2), rtol=1e-14)
        np.testing.assert_allclose(r.x, [1.0, 5.0], atol=1e-7)
    # Eq. (13) as printed takes the common mean from the better input, so the worse one
    # still pulls the fused mean: x_1 = a + (b - a) / d with d = 4.
    printed = ellipsoidal_intersection(xa, Pa, xb, Pb, eps=0.0, mutual_mean="as-printed")
    np.testing.assert_allclose(printed.x, [1.0 + (-3.0 - 1.0) / 4, 5.0 + (2.0 - 5.0) / 4])
    np.testing.assert_allclose(printed.P, np.eye(2), atol=1e-15)


def test_sijs_lazar_mean_passes_the_limiting_case_and_the_printed_one_does_not():
    """C_c = Pb (all of b's information is shared) must give the common mean xb."""
    Pa = random_spd(3, seed=4)
    Pb = Pa + random_spd(3, seed=5)  # Pb > Pa: EI's common covariance is Pb
    xa, xb = np.array([1.0, -2.0, 0.5]), np.array([3.0, 1.0, -1.0])
    for eps in (0.0, 1e-8):
        r = ellipsoidal_intersection(xa, Pa, xb, Pb, eps=eps)
        np.testing.assert_allclose(r.info["common_P"], Pb, rtol=1e-10)
        np.testing.assert_allclose(r.info["common_x"], xb, atol=1e-6)
        # b carries no independent information: the fusion is a
        np.testing.assert_allclose(r.x, xa, atol=1e-6)
        np.testing.assert_allclose(r.P, Pa, rtol=1e-10)
    printed = ellipsoidal_intersection(xa, Pa, xb, Pb, eps=0.0, mutual_mean="as-printed")
    np.testing.assert_allclose(printed.info["common_x"], xa, atol=1e-10)
    assert np.abs(printed.info["common_x"] - xb).max() > 1.0


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_equal_covariances_give_the_average_without_nan(mutual_mean):
    P = random_spd(3, seed=7)
    xa, xb = np.array([1.0, 0.0, 2.0]), np.array([-1.0, 4.0, 0.0])
    for eps in (0.0, 1e-8):
        r = ellipsoidal_intersection(xa, P, xb, P.copy(), eps=eps, mutual_mean=mutual_mean)
        np.testing.assert_allclose(r.x, (xa + xb) / 2, rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(r.P, P, rtol=1e-9)
        np.testing.assert_allclose(r.info["common_P"], P, rtol=1e-9)
        assert r.info["ties"] == 3


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
@pytest.mark.parametrize("relative", [1e-16, 1e-13, 1e-10, 1e-7, 1e-4])
def test_near_equal_covariances_give_finite_continuous_results(mutual_mean, relative):
    P = random_spd(2, seed=8)
    Pb = P + relative * random_spd(2, seed=9)
    xa, xb = np.array([1.0, 2.0]), np.array([0.0, -1.0])
    check_near_equal_covariances_are_finite(ellipsoidal_intersection, P, Pb, xa, xb,
                                            mutual_mean)
    r = ellipsoidal_intersection(xa, P, xb, Pb, mutual_mean=mutual_mean)
    if relative < 1e-12:  # far inside the regulariser's scale: the average of the means
        np.testing.assert_allclose(r.x, (xa + xb) / 2, atol=1e-3)
    exact = ellipsoidal_intersection(xa, P, xb, Pb, eps=0.0, mutual_mean=mutual_mean)
    if relative > 1e-6:  # far outside it: the regulariser is negligible
        np.testing.assert_allclose(r.x, exact.x, atol=1e-3)


def check_near_equal_covariances_are_finite(fn, P, Pb, xa, xb, mutual_mean):
    for eps in (0.0, 1e-8):
        r = fn(xa, P, xb, Pb, eps=eps, mutual_mean=mutual_mean)
        for value in (r.x, r.P, r.gains, r.info["common_x"], r.info["common_P"]):
            assert np.all(np.isfinite(value))
        assert np.all(np.linalg.eigvalsh(r.P) > 0)


# ----------------------------------------------------------------- EI: properties
pairs = st.integers(1, 4).flatmap(lambda n: st.tuples(spd_matrices(n), spd_matrices(n)))
means = st.floats(-5, 5, allow_nan=False)


@given(pairs, st.lists(means, min_size=8, max_size=8), st.sampled_from(["as-printed",
                                                                       "sijs-lazar"]),
       st.sampled_from([("information", 1e-8), ("information", 0.0), ("covariance", 0.01)]))
def test_ei_properties(Ps, values, mutual_mean, regularization):
    Pa, Pb = Ps
    n = Pa.shape[0]
    xa, xb = np.array(values[:n]), np.array(values[4:4 + n])
    regularizer, eps = regularization
    r = ellipsoidal_intersection(xa, Pa, xb, Pb, eps=eps, mutual_mean=mutual_mean,
                                 regularizer=regularizer)
    Cc = r.info["common_P"]
    scale = max(np.abs(Pa).max(), np.abs(Pb).max())
    # admissible common covariance (Definition 1) and eq. (8)
    assert np.linalg.eigvalsh(Cc - Pa).min() >= -1e-9 * scale
    assert np.linalg.eigvalsh(Cc - Pb).min() >= -1e-9 * scale
    np.testing.assert_allclose(inv(r.P), inv(Pa) + inv(Pb) - inv(Cc), rtol=1e-6,
                               atol=1e-8 * np.abs(inv(r.P)).max())
    np.testing.assert_array_equal(r.P, r.P.T)
    # honest gains
    np.testing.assert_allclose(r.gains[0] @ xa + r.gains[1] @ xb, r.x, atol=1e-8 * (1 + scale))
    np.testing.assert_allclose(r.gains.sum(axis=0), np.eye(n), atol=1e-8)
    if regularizer == "information":
        # the fused covariance is below both inputs and C_c is EI's minimal one
        assert np.linalg.eigvalsh(Pa - r.P).min() >= -1e-9 * scale
        assert np.linalg.eigvalsh(Pb - r.P).min() >= -1e-9 * scale
        d = np.linalg.eigvals(inv(Pa) @ Pb).real
        assert np.linalg.det(inv(Pa) @ Cc) == pytest.approx(np.prod(np.maximum(d, 1)),
                                                            rel=1e-6)


# ----------------------------------------------------------------- ill-conditioned inputs
# The conditioning contract: for condition numbers up to 1e12 (any scale 1e-12..1e12) EI
# returns a finite, exactly symmetric, positive definite P (issue 9, item 3: whitening
# with Pa squared the condition number and gave indefinite covariances).
MAX_CONDITION = 1e12  # the conditioning contract (docs/conventions.rst)

# EI's P from inputs with condition number kappa is accurate to about 1e-16 kappa in
# P's own metric (measured against a 60-digit reference: at most 1.3e-4 at 1e12).
METRIC_TOL = 1e-3


# The ordering P <= Pa, Pb (in P's metric) is a statement about the generalised
# eigenvalues of the pair; float64 resolves them to METRIC_TOL only where their spread is
# at most about 1e12 (beyond, eps * spread exceeds 1e-4 and the check measures rounding).
RESOLVED_SPREAD = 1e12


def resolved_pair(Pa, Pb):
    """Whether the generalised eigenvalues of (Pb, Pa) span at most RESOLVED_SPREAD."""
    w = scipy.linalg.eigh(Pb, Pa, eigvals_only=True)
    return w.max() <= RESOLVED_SPREAD * w.min()


def metric_difference(P, Q):
    """Largest |eigenvalue| of L^-1 (Q - P) L^-T, P = L L^T: relative in every direction."""
    L = np.linalg.cholesky(P)
    X = np.linalg.solve(L, np.linalg.solve(L, Q - P).T)
    return np.abs(np.linalg.eigvalsh(0.5 * (X + X.T))).max()


def assert_valid_fusion(r, Pa, Pb):
    """Finite, exactly symmetric, positive definite P (Cholesky); gains summing to I."""
    n = Pa.shape[-1]
    for value in (r.x, r.P, r.gains, r.info["common_x"], r.info["common_P"]):
        assert np.all(np.isfinite(value))
    np.testing.assert_array_equal(r.P, np.swapaxes(r.P, -1, -2))
    np.linalg.cholesky(r.P)  # raises if not positive definite
    eigenvalues = np.linalg.eigvalsh(r.P)
    # cond(P) <= 2 min(|Pa|, |Pb|) / min(lambda_min) <= 2e12 for inputs within the contract
    assert np.all(eigenvalues[..., 0] > 1e-13 * eigenvalues[..., -1])
    np.linalg.cholesky(r.info["common_P"])
    K = r.gains
    np.testing.assert_allclose(K.sum(axis=-3), np.broadcast_to(np.eye(n), K.shape[:-3] + (n, n)),
                               rtol=0, atol=1e-12 * (1 + np.abs(K).max()))


def condition_number(P):
    eigenvalues = np.linalg.eigvalsh(P)
    return eigenvalues[..., -1] / eigenvalues[..., 0]


def within_contract(*Ps):
    return all(np.all(condition_number(P) <= MAX_CONDITION) for P in Ps)


ill_pairs = st.integers(1, 5).flatmap(lambda n: st.booleans().flatmap(
    lambda common: ill_conditioned_sets(2, n, common_scale=common)))


@given(ill_pairs, st.lists(means, min_size=10, max_size=10),
       st.sampled_from(["as-printed", "sijs-lazar"]),
       st.sampled_from([("information", 1e-8), ("information", 0.0), ("covariance", 0.01)]))
def test_ei_is_positive_definite_on_ill_conditioned_pairs(Ps, values, mutual_mean,
                                                          regularization):
    Pa, Pb = Ps
    xa, xb = means_of_their_scale(values, Pa, Pb)
    regularizer, eps = regularization
    options = {"eps": eps, "mutual_mean": mutual_mean, "regularizer": regularizer}
    try:
        r = ellipsoidal_intersection(xa, Pa, xb, Pb, **options)
    except IllConditionedError:
        assert not within_contract(Pa, Pb)
        return
    assert_valid_fusion(r, Pa, Pb)
    np.testing.assert_allclose(r.gains[0] @ xa + r.gains[1] @ xb, r.x, rtol=1e-9,
                               atol=1e-9 * (np.abs(xa).max() + np.abs(xb).max()))
    if regularizer == "information" and resolved_pair(Pa, Pb):
        # EI takes the better input per direction: P <= Pa and P <= Pb, in P's metric
        for Q in (Pa, Pb):
            L = np.linalg.cholesky(r.P)
            X = np.linalg.solve(L, np.linalg.solve(L, Q).T)
            assert np.linalg.eigvalsh(0.5 * (X + X.T))[0] >= 1 - METRIC_TOL
        # symmetric in the two inputs
        swapped = ellipsoidal_intersection(xb, Pb, xa, Pa, **options)
        assert metric_difference(r.P, swapped.P) <= METRIC_TOL


@given(st.integers(1, 4).flatmap(lambda n: st.lists(ill_conditioned_sets(2, n), min_size=3,
                                                     max_size=3)),
       st.sampled_from(["as-printed", "sijs-lazar"]))
def test_ei_batched_ill_conditioned_pairs_equal_per_item(pairs_, mutual_mean):
    Pa = np.stack([p[0] for p in pairs_])
    Pb = np.stack([p[1] for p in pairs_])
    n = Pa.shape[-1]
    xa, xb = np.sqrt(np.diagonal(Pa, axis1=-2, axis2=-1)), np.zeros((3, n))
    r = ellipsoidal_intersection(xa, Pa, xb, Pb, mutual_mean=mutual_mean)
    assert_valid_fusion(r, Pa, Pb)
    for k in range(3):
        single = ellipsoidal_intersection(xa[k], Pa[k], xb[k], Pb[k], mutual_mean=mutual_mean)
        # LAPACK's batched and single paths round differently: agreement to the accuracy
        # the conditioning allows
        kappa = max(condition_number(Pa[k]), condition_number(Pb[k]))
        assert metric_difference(single.P, r.P[k]) <= 1e-14 * kappa + 1e-12


def issue_pair(rng, n, cond):
    """The construction of issue 9's reproducer: a rotated log-spaced spectrum."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    P = (Q * np.logspace(0, np.log10(cond), n)) @ Q.T
    return (P + P.T) / 2


def test_issue_reproducer_is_positive_definite_and_accurate():
    """rng(1), two 4x4 covariances with condition number 1e9: EI's P had eigenvalue -44.9.

    The expected eigenvalues are EI's exact covariance for these (rounded) inputs,
    computed with 60-digit arithmetic (mpmath) from eqs. (11)-(12).
    """
    check_issue_reproducer(ellipsoidal_intersection)


def check_issue_reproducer(fn):
    rng = np.random.default_rng(1)
    P1, P2 = issue_pair(rng, 4, 1e9), issue_pair(rng, 4, 1e9)
    r = fn(np.zeros(4), P1, np.zeros(4), P2)
    assert_valid_fusion(r, P1, P2)
    np.testing.assert_allclose(np.linalg.eigvalsh(r.P),
                               [0.754371179, 1.48154149, 767.535292, 63674.4010], rtol=1e-7)


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_random_pairs_at_condition_1e9_are_all_positive_definite(mutual_mean):
    """Issue 9: 31-40% of random pairs at condition number 1e9 gave an indefinite P."""
    check_random_pairs_at_condition_1e9(ellipsoidal_intersection, mutual_mean)


def check_random_pairs_at_condition_1e9(fn, mutual_mean):
    rng = np.random.default_rng(2024)
    Pa = np.stack([issue_pair(rng, 4, 1e9) for _ in range(200)])
    Pb = np.stack([issue_pair(rng, 4, 1e9) for _ in range(200)])
    xa, xb = rng.standard_normal((200, 4)), rng.standard_normal((200, 4))
    r = fn(xa, Pa, xb, Pb, mutual_mean=mutual_mean)
    assert_valid_fusion(r, Pa, Pb)


def reference_ei(xa, Pa, xb, Pb, mutual_mean):
    """Unregularised EI in Pa's whitened coordinates, eqs. (11)-(13), one direction at a time."""
    L = np.linalg.cholesky(Pa)
    d, U = np.linalg.eigh(inv(L) @ Pb @ inv(L).T)
    T = L @ U
    a, b = inv(T) @ xa, inv(T) @ xb
    alpha, beta = np.maximum(0, 1 - 1 / d), np.maximum(0, 1 / d - 1)
    R_a = (alpha if mutual_mean == "as-printed" else beta) / (alpha + beta)
    m = R_a * a + (1 - R_a) * b
    P_u = np.minimum(1, d)
    x_u = P_u * (a + b / d - np.minimum(1, 1 / d) * m)
    return T @ x_u, T @ np.diag(P_u) @ T.T, T @ np.diag(np.maximum(1, d)) @ T.T, T @ m


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_ei_agrees_with_the_whitened_closed_form_on_well_conditioned_inputs(mutual_mean, n):
    for seed in range(5):
        Pa, Pb = random_spd(n, seed=100 + seed), random_spd(n, seed=200 + seed, scale=2.0)
        g = np.random.default_rng(seed)
        xa, xb = g.standard_normal(n), g.standard_normal(n)
        x, P, Cc, mc = reference_ei(xa, Pa, xb, Pb, mutual_mean)
        r = ellipsoidal_intersection(xa, Pa, xb, Pb, eps=0.0, mutual_mean=mutual_mean)
        np.testing.assert_allclose(r.P, P, rtol=1e-10, atol=1e-12 * np.abs(P).max())
        np.testing.assert_allclose(r.x, x, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(r.info["common_P"], Cc, rtol=1e-10,
                                   atol=1e-12 * np.abs(Cc).max())
        np.testing.assert_allclose(r.info["common_x"], mc, rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------- argument forms
def check_argument_forms(fn, **options):
    """(xs, Ps) as sequences, stacked arrays, batches and columns equal the pairwise form."""
    xa, Pa, xb, Pb = setup_problem(3, 61)
    pairwise = fn(xa, Pa, xb, Pb, **options)
    forms = [fn([xa, xb], [Pa, Pb], **options), fn((xa, xb), (Pa, Pb), **options),
             fn(np.stack([xa, xb]), np.stack([Pa, Pb]), **options),
             fuse([(xa, Pa), (xb, Pb)], method=pairwise.method, **options)]
    # (a single matrix is factored by LAPACK directly, a stack through numpy's batched
    # LAPACK: the forms agree to rounding)
    def same(a, b):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)

    for r in forms:
        assert r.method == pairwise.method and r.weights is None
        same(r.x, pairwise.x)
        same(r.P, pairwise.P)
        same(r.gains, pairwise.gains)
        same(r.info["common_P"], pairwise.info["common_P"])
    # column vectors come back as columns
    column = fn([xa[:, None], xb[:, None]], [Pa, Pb], **options)
    assert column.x.shape == (3, 1)
    same(column.x[:, 0], pairwise.x)
    column = fn(np.stack([xa, xb])[..., None], np.stack([Pa, Pb]), **options)
    assert column.x.shape == (3, 1)
    # a batch (..., 2, n), with covariances broadcast against the means
    batch_x = np.stack([np.stack([xa, xb]), np.stack([xb, xa]), np.stack([xa, xa])])
    r = fn(batch_x, np.stack([Pa, Pb]), **options)
    assert r.x.shape == (3, 3) and r.P.shape == (3, 3, 3) and r.gains.shape == (3, 2, 3, 3)
    for k in range(3):
        single = fn(batch_x[k, 0], Pa, batch_x[k, 1], Pb, **options)
        np.testing.assert_allclose(r.x[k], single.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r.P[k], single.P, rtol=1e-9, atol=1e-12)
    # a sequence of batched means
    r2 = fn([batch_x[:, 0], batch_x[:, 1]], [Pa, Pb], **options)
    np.testing.assert_array_equal(r2.x, r.x)


def check_argument_form_errors(fn, option):
    xa, Pa, xb, Pb = setup_problem(2, 62)
    with pytest.raises(ValueError, match="exactly two estimates, got 3"):
        fn([xa, xb, xa], [Pa, Pb, Pa])
    with pytest.raises(ValueError, match="exactly two estimates, got 3"):
        fuse([(xa, Pa), (xb, Pb), (xa, Pb)], method=fn(xa, Pa, xb, Pb).method)
    with pytest.raises(ValueError, match="at least 2 estimates"):
        fn([xa], [Pa])
    with pytest.raises(TypeError, match="positional arguments"):
        fn(xa, Pa, xb, Pb, 0.01, 0.01)
    with pytest.raises(TypeError, match=f"third must be {option}"):
        fn(xa, Pa, xb)
    with pytest.raises(TypeError, match=f"{option} both"):
        fn(xa, Pa, xb, Pb, 0.01, **{option: 0.02})
    # the positional option is the keyword option, in both forms
    np.testing.assert_array_equal(fn([xa, xb], [Pa, Pb], 0.01).P,
                                  fn([xa, xb], [Pa, Pb], **{option: 0.01}).P)
    np.testing.assert_array_equal(fn(xa, Pa, xb, Pb, 0.01).x,
                                  fn(xa, Pa, xb, Pb, **{option: 0.01}).x)


def test_argument_forms_agree():
    check_argument_forms(ellipsoidal_intersection)
    check_argument_forms(ellipsoidal_intersection, mutual_mean="as-printed", eps=0.01,
                         regularizer="covariance")


def test_argument_form_errors():
    check_argument_form_errors(ellipsoidal_intersection, "eps")


# ----------------------------------------------------------------- batching and conventions
def check_batched_equals_per_item(fn, mutual_mean):
    batch = (3, 4)
    n = 2
    Pa, Pb = random_spd(n, batch, seed=40), random_spd(n, batch, seed=41)
    Pb[0, 0] = Pa[0, 0]  # a tie (closed form for PC)
    Pb[0, 1] = Pa[0, 1] + random_spd(n, seed=42)  # dominated
    g = np.random.default_rng(4)
    xa, xb = g.standard_normal(batch + (n,)), g.standard_normal(batch + (n,))
    xb[1, 1] = xa[1, 1]  # equal means
    xb[2, 3] = xa[2, 3] + 20  # infeasible for PC
    r = fn(xa, Pa, xb, Pb, mutual_mean=mutual_mean)
    assert r.x.shape == batch + (n,) and r.P.shape == batch + (n, n)
    assert r.gains.shape == batch + (2, n, n)
    assert r.info["common_P"].shape == batch + (n, n)
    for index in np.ndindex(*batch):
        single = fn(xa[index], Pa[index], xb[index], Pb[index], mutual_mean=mutual_mean)
        np.testing.assert_allclose(r.x[index], single.x, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(r.P[index], single.P, rtol=1e-7, atol=1e-10)
        np.testing.assert_allclose(r.info["common_P"][index], single.info["common_P"],
                                   rtol=1e-6, atol=1e-10)


@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_batched_equals_per_item(mutual_mean):
    check_batched_equals_per_item(ellipsoidal_intersection, mutual_mean)


def check_broadcast_and_columns(fn):
    Pa, Pb = random_spd(2, seed=1), random_spd(2, seed=2)
    xs = np.random.default_rng(0).standard_normal((5, 2))
    r = fn(xs, Pa, np.zeros(2), Pb)
    assert r.x.shape == (5, 2) and r.P.shape == (5, 2, 2)
    column = fn(xs[0].reshape(2, 1), Pa, np.zeros((2, 1)), Pb)
    assert column.x.shape == (2, 1)
    np.testing.assert_allclose(column.x[:, 0], r.x[0], rtol=1e-10)


def test_batch_axes_broadcast_and_column_vectors_come_back_as_columns():
    check_broadcast_and_columns(ellipsoidal_intersection)


def check_inputs_are_not_mutated(fn, **options):
    xa, Pa, xb, Pb = setup_problem(3, 5)
    Pb = Pb.copy()
    Pb[0, 1] += 1e-13  # slightly asymmetric, within tolerance
    xs, Ps = np.stack([xa, xb]), np.stack([Pa, Pb])
    columns = [xa[:, None].copy(), xb[:, None].copy()]
    arrays = (xa, Pa, xb, Pb, xs, Ps, *columns)
    copies = [v.copy() for v in arrays]
    fn(xa, Pa, xb, Pb, **options)
    fn(xs, Ps, **options)
    fn([xa, xb], [Pa, Pb], **options)
    fn(columns, [Pa, Pb], **options)
    fn(xs[None], Ps, **options)
    fuse([(xa, Pa), (xb, Pb)], method=fn(xs, Ps).method, **options)
    for before, after in zip(copies, arrays):
        np.testing.assert_array_equal(before, after)


def test_inputs_are_not_mutated():
    check_inputs_are_not_mutated(ellipsoidal_intersection, mutual_mean="as-printed")
    check_inputs_are_not_mutated(ellipsoidal_intersection, eps=0.01, regularizer="covariance")


def check_registry_and_filters(name, fn):
    xa, Pa, xb, Pb = setup_problem(2, 6)
    assert name in cifilter.available_methods()
    record = cifilter.get_method(name)
    assert record.guarantee == "none" and record.function is fn and record.core is not None
    assert record.weights.startswith("None")
    direct = fn(xa, Pa, xb, Pb, mutual_mean="as-printed")
    through = fuse([(xa, Pa), (xb, Pb)], method=name, mutual_mean="as-printed")
    np.testing.assert_array_equal(through.x, direct.x)
    np.testing.assert_array_equal(through.P, direct.P)
    kf = cifilter.KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P = xa.reshape(2, 1).copy(), Pa.copy()
    result = kf.fuse((xb, Pb), method=name)
    assert kf.x.shape == (2, 1)
    np.testing.assert_allclose(kf.x[:, 0], fn(xa, Pa, xb, Pb).x, rtol=1e-12)
    assert kf.last_fusion is result and result.weights is None


def test_registry_and_filters():
    check_registry_and_filters("ei", ellipsoidal_intersection)
    xa, Pa, xb, Pb = setup_problem(2, 6)
    with pytest.raises(TypeError, match="alpha"):
        fuse([(xa, Pa), (xb, Pb)], method="ei", alpha=0.05)
    with pytest.raises(TypeError, match="tol"):
        fuse([(xa, Pa), (xb, Pb)], method="ei", tol=1e-3)


def test_demo_rows_run_batched():
    import io

    from cifilter.cli.demo import run_demo

    rows = run_demo(runs=2, steps=20, methods=["ei"], out=io.StringIO())
    for row in rows[2:]:
        assert "error" not in row and np.isfinite(row["mean_nees"])


# ----------------------------------------------------------------- bad input
BAD_INPUT = [
    ((np.zeros(2), np.eye(2), np.zeros(3), np.eye(3)), {}, ValueError, "Pa is 2x2 but Pb"),
    ((np.zeros(3), np.eye(2), np.zeros(2), np.eye(2)), {}, ValueError, "xa must have shape"),
    ((np.zeros(2), np.eye(2), np.zeros(2), -np.eye(2)), {}, ValueError,
     "Pb is not positive definite"),
    ((np.zeros(2), np.eye(2), np.zeros(2), [[1.0, 0.5], [0.0, 1.0]]), {}, ValueError,
     "not symmetric"),
    ((np.array([np.nan, 0.0]), np.eye(2), np.zeros(2), np.eye(2)), {}, ValueError,
     "non-finite"),
    ((np.zeros(2), np.eye(2), np.zeros(2), "eye"), {}, TypeError, "numeric"),
    ((np.zeros((3, 2)), np.eye(2), np.zeros((4, 2)), np.eye(2)), {}, ValueError,
     r"xa \(3,\), Pa \(\), xb \(4,\), Pb \(\) do not broadcast"),
    ((np.zeros(2), np.eye(2), np.zeros(2), np.eye(2)), {"eps": -1.0}, ValueError, "eps"),
    ((np.zeros(2), np.eye(2), np.zeros(2), np.eye(2)), {"mutual_mean": "mean"}, ValueError,
     "mutual_mean"),
    ((np.zeros(2), np.eye(2), np.zeros(2), np.eye(2)), {"regularizer": "both"}, ValueError,
     "regularizer"),
    (([np.zeros(2), np.zeros(3)], [np.eye(2), np.eye(2)]), {}, ValueError, r"xs\[1\]"),
    ((np.zeros((2, 2)), [np.eye(2), -np.eye(2)]), {}, ValueError,
     r"Ps\[1\] is not positive definite"),
]


@pytest.mark.parametrize("args, kwargs, error, message", BAD_INPUT)
def test_bad_input_is_named(args, kwargs, error, message):
    with pytest.raises(error, match=message):
        ellipsoidal_intersection(*args, **kwargs)


@pytest.mark.parametrize("regularization", [("covariance", 0.01), ("information", 1e-8)])
@pytest.mark.parametrize("mutual_mean", ["as-printed", "sijs-lazar"])
def test_equal_inputs_at_large_scales_have_a_finite_mutual_mean(regularization, mutual_mean):
    """Regression (found by hypothesis): two equal covariances of order 1e14 with the
    covariance regulariser eps I (below rounding at that scale) made A + B = 0 and the
    mutual mean of eq. (13) 0/0 (NaN x). The symmetric limit gives their average."""
    regularizer, eps = regularization
    P = np.diag([1e14, 1e12, 1e12])
    xa, xb = np.array([1e6, 0.0, 2e6]), np.array([3e6, 1e6, 0.0])
    r = ellipsoidal_intersection(xa, P, xb, P.copy(), mutual_mean=mutual_mean,
                                 regularizer=regularizer, eps=eps)
    assert np.isfinite(r.x).all() and np.isfinite(r.info["common_x"]).all()
    np.testing.assert_allclose(r.x, 0.5 * (xa + xb), rtol=1e-9)
