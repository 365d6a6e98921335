"""The exact worst case of fixed fusion gains over every admissible joint covariance.

For gains ``K_i`` (with ``sum_i K_i = I``) the fused error is ``e = sum_i K_i e_i``. Along a
direction ``v`` put ``a_i = K_i^T v`` and ``s_i = ||L_i^T a_i||`` (``P_i = L_i L_i^T``). Over
every joint covariance whose diagonal blocks are the ``P_i`` and whose normalised cross
blocks ``C_ij = L_i^-1 P_ij L_j^-T`` have spectral norm at most ``rho``, the largest error
variance along ``v`` is

    worst(v) = (1 - rho) sum_i s_i^2 + rho (sum_i s_i)^2,

attained by ``C_ij = rho u_i u_j^T`` with ``u_i = L_i^T a_i / s_i`` (a positive
semidefinite joint). ``rho = 1`` is arbitrary correlation (Covariance Intersection),
``rho = 0`` independence. A fused covariance ``P`` is a valid bound for the gains exactly
when ``v^T P v >= worst(v)`` for every ``v``.

Random joints are far from this worst case; these helpers check it exactly, at the
eigenvectors of ``P`` and at directions that locally maximise ``worst(v) / v^T P v``.
"""

import numpy as np

EPS = np.finfo(float).eps


def _factors(gains, Ps):
    """``M_i = K_i L_i`` in extended precision (so the check itself adds no rounding)."""
    Ls = np.linalg.cholesky(np.asarray(Ps, dtype=float))
    K = np.asarray(gains, dtype=np.longdouble)
    return np.einsum("...kij,...kjl->...kil", K, Ls.astype(np.longdouble))


def worst_case_variance(gains, Ps, v, rho=1.0):
    """``worst(v)`` for directions ``v`` (..., n) (see the module docstring)."""
    M = _factors(gains, Ps)
    s = np.linalg.norm(
        np.einsum("...kij,...i->...kj", M, np.asarray(v, dtype=np.longdouble)).astype(float),
        axis=-1,
    )
    return (1.0 - rho) * (s**2).sum(axis=-1) + rho * s.sum(axis=-1) ** 2


def _ascend(M, P, v, rho, steps=30):
    """Fixed-point ascent of ``worst(v) / v^T P v`` from ``v``.

    With ``t_i`` proportional to ``s_i(v)``, ``worst(v) <= v^T B(t) v`` where
    ``B(t) = (1 - rho) sum_i M_i M_i^T + rho sum_i M_i M_i^T / t_i`` with equality at ``v``;
    the top generalised eigenvector of ``(B(t), P)`` is the next direction.
    """
    Mf = M.astype(float)
    grams = np.einsum("kij,klj->kil", Mf, Mf)
    L = np.linalg.cholesky(P)
    for _ in range(steps):
        s = np.linalg.norm(np.einsum("kij,i->kj", Mf, v), axis=-1)
        if s.sum() == 0:
            return v
        t = np.maximum(s / s.sum(), 1e-300)
        B = (1.0 - rho) * grams.sum(0) + rho * np.einsum("k,kij->ij", 1.0 / t, grams)
        Li = np.linalg.inv(L)
        S = Li @ B @ Li.T
        _, U = np.linalg.eigh(0.5 * (S + S.T))
        w = np.linalg.solve(L.T, U[:, -1])
        w = w / np.linalg.norm(w)
        if abs(abs(w @ v) - 1.0) < 1e-14:
            return w
        v = w
    return v


def worst_violation(P, gains, Ps, rho=1.0, tol=None):
    """Largest ``(worst(v) - v^T P v)`` beyond the rounding tolerance, over checked ``v``.

    Checks the eigenvectors of ``P`` and the directions reached by ascent from each of them.
    Returns ``(excess, v)`` where ``excess <= 0`` means the bound holds at every checked
    direction; the tolerance is ``tol * ||P||`` with ``tol`` defaulting to ``64 n N eps``
    (rounding of the products that form ``P``: the bound is exact for the returned gains).
    """
    P = np.asarray(P, dtype=float)
    n = P.shape[-1]
    count = len(gains)
    if tol is None:
        tol = 64.0 * n * count * EPS
    M = _factors(gains, Ps)
    norm = np.linalg.norm(P, 2)
    _, vectors = np.linalg.eigh(P)
    starts = [vectors[:, k] for k in range(n)]
    candidates = starts + [_ascend(M, P, v, rho) for v in starts]
    worst_excess, worst_v = -np.inf, None
    for v in candidates:
        v = v / np.linalg.norm(v)
        excess = float(worst_case_variance(gains, Ps, v, rho) - v @ P @ v) - tol * norm
        if excess > worst_excess:
            worst_excess, worst_v = excess, v
    return worst_excess, worst_v


def assert_bound_holds(P, gains, Ps, rho=1.0, tol=None, what="P"):
    """Assert that ``P`` dominates the worst-case error covariance of ``gains``."""
    excess, v = worst_violation(P, gains, Ps, rho, tol)
    assert excess <= 0.0, (
        f"{what} is not a bound: along v = {v.tolist()} the worst admissible error variance "
        f"exceeds v^T P v by {excess:.3g} beyond rounding (||P|| = {np.linalg.norm(P, 2):.3g})"
    )


def assert_unbiased(gains, tol=None):
    """Assert ``sum_i K_i = I`` to rounding (the fused error is then ``sum_i K_i e_i``)."""
    gains = np.asarray(gains, dtype=float)
    n = gains.shape[-1]
    scale = 1.0 + np.abs(gains).sum(axis=-3).max()
    tol = 64.0 * n * EPS * scale if tol is None else tol
    residual = np.abs(gains.sum(axis=-3) - np.eye(n)).max()
    assert residual <= tol * max(1.0, np.abs(gains).max()), f"sum of gains - I = {residual:.3g}"
