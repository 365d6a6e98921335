"""Hypothesis strategies for covariances, admissible joint covariances and linear models.

``joint_covariances`` builds every kind of cross-covariance the fusion rules must survive:
independent, partially and fully correlated (rank-deficient correlation), by whitening
a random Gram matrix block by block so that the diagonal blocks are exactly the given
covariances.
"""

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)


@st.composite
def spd_matrices(draw, n, min_eigenvalue=0.05, max_eigenvalue=20.0):
    """Symmetric positive definite n x n matrices with bounded condition number."""
    A = draw(arrays(float, (n, n), elements=finite))
    Q, _ = np.linalg.qr(A + 1e-3 * np.eye(n))
    eigenvalues = draw(
        arrays(float, (n,), elements=st.floats(min_eigenvalue, max_eigenvalue))
    )
    P = (Q * eigenvalues) @ Q.T
    return 0.5 * (P + P.T)


@st.composite
def covariance_sets(draw, count, n):
    """A list of ``count`` covariances of dimension n."""
    return [draw(spd_matrices(n)) for _ in range(count)]


def _inverse_sqrt(S):
    eigenvalues, vectors = np.linalg.eigh(S)
    return (vectors / np.sqrt(eigenvalues)) @ vectors.T


def joint_from_correlation(Ps, Z):
    """Joint covariance with diagonal blocks ``Ps`` from a random factor ``Z`` (N*n x k)."""
    count, n = len(Ps), Ps[0].shape[0]
    S = Z @ Z.T + 1e-9 * np.eye(count * n)
    D = np.zeros_like(S)
    for i in range(count):
        block = slice(i * n, (i + 1) * n)
        D[block, block] = np.linalg.cholesky(Ps[i]) @ _inverse_sqrt(S[block, block])
    joint = D @ S @ D.T
    joint = 0.5 * (joint + joint.T)
    for i in range(count):  # exact diagonal blocks
        block = slice(i * n, (i + 1) * n)
        joint[block, block] = Ps[i]
    return joint


@st.composite
def joint_covariances(draw, Ps):
    """An admissible joint covariance (positive semidefinite) with diagonal blocks ``Ps``."""
    count, n = len(Ps), Ps[0].shape[0]
    rank = draw(st.integers(1, count * n))  # small rank: strongly/fully correlated
    Z = draw(arrays(float, (count * n, rank), elements=finite))
    Z = Z + 1e-3 * np.eye(count * n, rank)
    return joint_from_correlation(Ps, Z)


def fused_error_covariance(gains, joint):
    """Covariance of sum_i K_i e_i when the stacked errors have covariance ``joint``."""
    K = np.concatenate(list(gains), axis=-1)  # [K_1 ... K_N], n x N*n
    return K @ joint @ K.T


def assert_psd(M, tol=1e-8, what="matrix"):
    """Assert that a symmetric matrix is positive semidefinite up to a relative tolerance."""
    smallest = np.linalg.eigvalsh(0.5 * (M + M.T))[0]
    scale = max(1.0, float(np.abs(M).max()))
    assert smallest >= -tol * scale, f"{what} has eigenvalue {smallest:.3g} < 0"


@st.composite
def rho_bounded_joints(draw, Ps, rho):
    """A joint covariance with diagonal blocks Ps that satisfies Definition 2 for ``rho``.

    J = blockdiag((1 - rho_i) P_i) + M with M positive semidefinite and diagonal blocks
    rho_i P_i (zero rows and columns where rho_i = 0); then P_m^(rho) = M >= 0 (eq. (21)).
    M comes from a random factor of random rank, so fully correlated parts occur.
    """
    count, n = len(Ps), Ps[0].shape[0]
    rho = np.broadcast_to(np.asarray(rho, dtype=float), (count,))
    joint = np.zeros((count * n, count * n))
    # rho_i P_i with a denormal rho_i is not numerically positive definite; such vectors get
    # no cross-covariance (admissible for every rho_i >= 0)
    inside = [i for i in range(count) if rho[i] > 1e-9]
    if inside:
        k = len(inside) * n
        rank = draw(st.integers(1, k))
        Z = draw(arrays(float, (k, rank), elements=finite)) + 1e-3 * np.eye(k, rank)
        M = joint_from_correlation([rho[i] * Ps[i] for i in inside], Z)
        index = np.concatenate([np.arange(i * n, (i + 1) * n) for i in inside])
        joint[np.ix_(index, index)] = M
    for i in range(count):
        block = slice(i * n, (i + 1) * n)
        joint[block, block] += (1 - rho[i]) * Ps[i] if i in inside else Ps[i]
    return joint


def sets_with_joint(count, n, per_estimate):
    """(Ps, rho, joint) with joint satisfying Definition 2 for rho."""
    rho = (arrays(float, (count,), elements=st.floats(0.0, 1.0)) if per_estimate
           else st.floats(0.0, 1.0))
    return st.tuples(covariance_sets(count, n), rho).flatmap(
        lambda t: st.tuples(st.just(t[0]), st.just(t[1]), rho_bounded_joints(t[0], t[1])))


# ----------------------------------------------------------------- ill-conditioned inputs
# Tracking covariances mix units and scales: condition numbers of 1e8..1e12 and overall
# scales of 1e-12..1e12 are ordinary inputs. Two kinds of ill-conditioning occur and both
# are drawn: a rotated spectrum (a nearly unobservable combination of states) and a graded
# diagonal scaling of a well-conditioned matrix (mixed units, biases with tiny variance).
MAX_CONDITION = 1e12


def _random_orthogonal(draw, n):
    A = draw(arrays(float, (n, n), elements=finite))
    Q, R = np.linalg.qr(A + 1e-3 * np.eye(n))
    return Q * np.where(np.diag(R) < 0, -1.0, 1.0)


@st.composite
def ill_conditioned_spd(draw, n, max_condition=MAX_CONDITION, scales=(1e-12, 1e12)):
    """SPD n x n matrices with condition number up to ``max_condition`` and any scale.

    Half of the draws rotate a log-spread spectrum, half scale a well-conditioned matrix
    by a graded diagonal (``D C D``: mixed units); the overall scale is log-uniform in
    ``scales``. The condition number of the result is at most about ``max_condition``.
    """
    log_cond = draw(st.floats(0.0, np.log10(max_condition)))
    log_scale = draw(st.floats(np.log10(scales[0]), np.log10(scales[1])))
    if draw(st.booleans()) or n == 1:
        Q = _random_orthogonal(draw, n)
        inner = draw(arrays(float, (max(n - 2, 0),), elements=st.floats(0.0, 1.0)))
        exponents = np.sort(np.concatenate([[0.0, 1.0][:n], inner]))[::-1] * log_cond
        P = (Q * 10.0 ** (exponents + log_scale)) @ Q.T
    else:
        C = draw(spd_matrices(n, 0.5, 2.0))  # condition number at most 4
        d = np.sqrt(draw(arrays(float, (n,), elements=st.floats(0.0, 1.0))))
        d = d - d.min()
        d = 10.0 ** (0.5 * (log_cond - np.log10(4.0)) * d / max(d.max(), 1e-300)
                     + 0.5 * log_scale)
        P = (d[:, None] * C) * d[None, :]
    return 0.5 * (P + P.T)


@st.composite
def ill_conditioned_sets(draw, count, n, max_condition=MAX_CONDITION, common_scale=True):
    """``count`` ill-conditioned covariances of dimension n.

    With ``common_scale`` the matrices share one overall scale (estimates of one state in
    one unit system); otherwise every matrix has its own scale in 1e-12..1e12.
    """
    if common_scale:
        log_scale = draw(st.floats(-12.0, 12.0))
        scales = (10.0 ** log_scale, 10.0 ** log_scale)
        return [draw(ill_conditioned_spd(n, max_condition, scales)) for _ in range(count)]
    return [draw(ill_conditioned_spd(n, max_condition)) for _ in range(count)]


@st.composite
def partial_state_problems(draw):
    """Estimates of parts ``H_i x`` of a state: N = 2..4 estimates of a state of dimension
    2..4, the first of the full state or not, the others of random H_i (1 <= m_i <= n + 1
    rows), covariances of condition number up to 1e12 at one scale in 1e-12..1e12; the
    estimates together observe the state. Returns ``(Hs, Ps, n)`` (None in Hs: the full
    state)."""
    n = draw(st.integers(2, 4))
    count = draw(st.integers(2, 4))
    log_scale = draw(st.floats(-12.0, 12.0))
    scales = (10.0**log_scale, 10.0**log_scale)
    g = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    Hs, Ps = [], []
    first_full = draw(st.booleans())
    for i in range(count):
        if i == 0 and first_full:
            Hs.append(None)
            Ps.append(draw(ill_conditioned_spd(n, scales=scales)))
            continue
        m = draw(st.integers(1, n + 1))
        Hs.append(g.standard_normal((m, n)))
        Ps.append(draw(ill_conditioned_spd(m, scales=scales)))
    if not first_full:  # make sure the state is observed: one more estimate of all of it
        Hs.append(g.standard_normal((n, n)) + 3 * np.eye(n))
        Ps.append(draw(ill_conditioned_spd(n, scales=scales)))
    return Hs, Ps, n


def means_of_their_scale(values, Pa, Pb):
    """Two means of the size of their standard deviations, from 10 unit values."""
    n = Pa.shape[0]
    return (np.array(values[:n]) * np.sqrt(np.diag(Pa)),
            np.array(values[5:5 + n]) * np.sqrt(np.diag(Pb)))


# ----------------------------------------------------------------- models for cifilter.horizon
@st.composite
def systems(draw, n=2):
    """(F, Q, H, R, PA, PB): a random linear model of dimension n and two covariances."""
    g = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    F = g.standard_normal((n, n)) * draw(st.sampled_from([0.3, 1.0]))
    Q = draw(spd_matrices(n, min_eigenvalue=0.01, max_eigenvalue=5.0))
    H = g.standard_normal((draw(st.integers(1, n)), n))
    R = np.eye(H.shape[0]) * draw(st.sampled_from([0.1, 1.0, 10.0]))
    PA, PB = draw(spd_matrices(n)), draw(spd_matrices(n))
    return F, Q, H, R, PA, PB


@st.composite
def models(draw, n, measured=None):
    """(F, Q, H, R) with a spectral radius from 0.3 to 1.25 (stable and unstable)."""
    g = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    A = g.standard_normal((n, n))
    radius = draw(st.sampled_from([0.3, 0.9, 1.0, 1.05, 1.25]))
    F = A * radius / np.abs(np.linalg.eigvals(A)).max()
    Q = draw(ill_conditioned_spd(n, max_condition=1e6, scales=(1e-6, 1e2)))
    if measured is None:
        measured = draw(st.booleans())
    if not measured:
        return F, Q, None, None
    H = g.standard_normal((draw(st.integers(1, n)), n))
    R = draw(ill_conditioned_spd(H.shape[0], max_condition=1e6, scales=(1e-6, 1e2)))
    return F, Q, H, R
